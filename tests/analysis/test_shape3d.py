"""The report's 3D shapes (analysis/shape3d.py): the surface of points as an alpha shape, floaters left out."""
from __future__ import annotations

import numpy as np

from odsplat.analysis.shape3d import alpha_faces, drop_floaters


def _sphere(n: int, radius: float, centre=(0.0, 0.0, 0.0)) -> np.ndarray:
    """n points spread evenly over a sphere (a Fibonacci lattice)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1) + centre


def test_points_on_a_ball_give_its_closed_skin():
    """Gaussians lie on a surface give or take their size: a shell 1 cm thick over a 10 cm ball gives a skin with
    no hole (each edge between faces in pairs) on the shell, none across the ball's inside."""
    rng = np.random.default_rng(1)
    p = _sphere(800, 0.1) * rng.uniform(0.95, 1.05, (800, 1))
    faces = alpha_faces(p)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [0, 2]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    # closed: no edge on one face only (an alpha shape may pinch, two pairs of faces on one edge, in a few places)
    assert len(faces) > len(p) and np.all(counts % 2 == 0) and np.mean(counts == 2) > 0.9, np.bincount(counts)
    centres = p[faces].mean(axis=1)
    assert np.linalg.norm(centres, axis=1).min() > 0.085


def test_a_plate_is_a_skin_and_a_stray_cluster_beside_it_goes():
    g = np.linspace(0, 0.4, 21)
    x, y = np.meshgrid(g, g)
    plate = np.concatenate([np.stack([x.ravel(), y.ravel(), np.full(x.size, z)], axis=1) for z in (0.0, 0.01)])
    stray = _sphere(12, 0.005, centre=(0.8, 0.8, 0.3))
    p = np.concatenate([plate, stray])
    keep, faces = drop_floaters(p, alpha_faces(p))
    assert set(keep) == set(range(len(plate)))             # the plate whole, the floater gone
    assert faces.max() < len(keep) and len(faces) > 2 * len(plate) * 0.9
    assert len(alpha_faces(p[:10])) == 0                     # too few points for a skin: drawn as points


def test_a_shapes_file_edited_by_hand_is_refused_naming_what_is_wrong():
    import json

    import pytest

    from odsplat.analysis.shape3d import KIND, parse_shapes

    good = {"kind": KIND, "schema": 1, "surface": {"points_m": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]],
                                                   "lines": []},
            "modes": [{"mode": 1, "judged": True, "re": [[0, 0, 1]] * 3, "im": [[0, 0, 0]] * 3}]}
    assert parse_shapes(json.dumps(good).encode())["faces"].tolist() == [[0, 1, 2]]
    for change, words in ((lambda d: d["surface"].update(faces=[[0, 1, 7]]), "surface.faces: an index names no point"),
                          (lambda d: d["modes"][0].update(re=[[0, 0, "x"]] * 3), "not a 3D shapes file"),
                          (lambda d: d["modes"][0].update(im=[[0, 0, float("nan")]] * 3), "modes[0].im: expected"),
                          (lambda d: d.update(kind="odsplat.analysis"), "expected kind"),
                          (lambda d: d["surface"].pop("points_m"), "not a 3D shapes file")):
        bad = json.loads(json.dumps(good))
        change(bad)
        with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
            parse_shapes(json.dumps(bad).encode())
    with pytest.raises(ValueError, match="not a 3D shapes file"):
        parse_shapes(b"\xff\xfe")
