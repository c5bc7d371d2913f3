"""Each mode's shape in 3D for the report's interactive view (plots/shapes3d.json, drawn by plotly.js in the page):
the structure's surface as triangles, each mode's complex displacement at their corners, and whether the mode stood
above the video's noise floor.

The surface is the alpha shape of the points the shapes are known at (the Gaussians' rest positions, subsampled
evenly to MAX_VERTICES): the boundary faces of the Delaunay tetrahedra whose circumsphere is smaller than
ALPHA_SPACING times the points' median spacing. Points on a surface give its skin; a hole wider than that stays
open. Where there are too few points for a skin (the accelerometers alone), the shape is drawn as points joined by
the geometry's trace lines (outputs.sensor_lines)."""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from odsplat.spine.atomic import atomic_write_text

if TYPE_CHECKING:
    from .result import AnalysisResult

log = logging.getLogger(__name__)

KIND = "odsplat.shapes3d"
SCHEMA = 1
MAX_VERTICES = 1500     # the page's size: about 60 bytes a vertex and mode
ALPHA_SPACING = 2.5     # the alpha shape's radius over the median nearest-neighbour spacing
MIN_MESH_POINTS = 20    # fewer points than this are drawn as points and lines
MIN_PART_SHARE = 0.05   # a connected part of the surface with fewer of its points than this is a floater
DIGITS = 5              # significant digits kept in the file


def alpha_faces(points_m: np.ndarray, spacing_factor: float = ALPHA_SPACING) -> np.ndarray:
    """(F, 3) vertex indices of the alpha shape's boundary triangles over `points_m` ((N, 3)); empty where the
    points span no volume."""
    p = np.asarray(points_m, float)
    if len(p) < MIN_MESH_POINTS:
        return np.zeros((0, 3), int)
    d, _ = cKDTree(p).query(p, k=2)
    alpha = spacing_factor * float(np.median(d[:, 1]))
    try:
        tets = Delaunay(p).simplices
    except QhullError:          # flat or degenerate
        return np.zeros((0, 3), int)
    a = p[tets[:, 0]]
    edges = p[tets[:, 1:]] - a[:, None, :]                       # (T, 3, 3)
    rhs = 0.5 * np.sum(edges ** 2, axis=2)                        # (T, 3)
    det = np.linalg.det(edges)
    ok = np.abs(det) > 1e-12 * np.maximum(np.sum(edges ** 2, axis=(1, 2)), 1e-300) ** 1.5
    radius = np.full(len(tets), np.inf)
    radius[ok] = np.linalg.norm(np.linalg.solve(edges[ok], rhs[ok][..., None])[..., 0], axis=1)
    kept = tets[radius < alpha]
    if not len(kept):
        return np.zeros((0, 3), int)
    faces = np.concatenate([kept[:, [0, 1, 2]], kept[:, [0, 1, 3]], kept[:, [0, 2, 3]], kept[:, [1, 2, 3]]])
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def drop_floaters(points_m: np.ndarray, faces: np.ndarray,
                  min_share: float = MIN_PART_SHARE) -> tuple[np.ndarray, np.ndarray]:
    """(kept point indices, faces renumbered to them): the surface's connected parts holding at least `min_share` of
    its triangulated points; a stray Gaussian beside the structure (a floater) and a point on no triangle go. The
    points unchanged where there are no faces."""
    n = len(points_m)
    if not len(faces):
        return np.arange(n), faces
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [0, 2]]])
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    on_face = np.zeros(n, bool)
    on_face[faces.ravel()] = True
    sizes = np.bincount(label[on_face], minlength=label.max() + 1)
    big = sizes >= max(min_share * on_face.sum(), 3)
    keep = np.flatnonzero(on_face & big[label])
    new_index = np.full(n, -1)
    new_index[keep] = np.arange(len(keep))
    kept_faces = new_index[faces]
    return keep, kept_faces[(kept_faces >= 0).all(axis=1)]


def surface_mesh(points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The structure's surface as the report and the viewer draw it: (the indices of the points it keeps, (F, 3)
    faces over them): at most MAX_VERTICES of the points, evenly (`outputs.surface_subset`), their alpha shape
    (`alpha_faces`) less its floaters (`drop_floaters`). No faces where the points span no volume."""
    from .outputs import surface_subset

    p = np.asarray(points_m, float)
    pick = surface_subset(len(p), MAX_VERTICES)
    keep, faces = drop_floaters(p[pick], alpha_faces(p[pick]))
    return pick[keep], faces


def _rounded(x: np.ndarray) -> list:
    """Numbers to DIGITS significant digits (relative to the array's largest), as nested lists for JSON."""
    x = np.asarray(x, float)
    top = float(np.max(np.abs(x))) if x.size else 0.0
    if top == 0 or not np.isfinite(top):
        return np.nan_to_num(x).tolist()
    step = 10.0 ** (np.floor(np.log10(top)) - DIGITS + 1)
    return (np.round(np.nan_to_num(x) / step) * step).tolist()


def shapes_document(result: AnalysisResult) -> dict | None:
    """What the page draws: {"kind", "schema", "surface": {"points_m", "faces", "lines"}, "modes": [...]}, each
    mode {"mode", "freq_hz", "damping", "source", "judged" (above the video's noise floor), "re", "im"} (its
    displacement at the points, (N, 3), normalised to a largest amplitude of 1). None where no shape can be drawn."""
    from .outputs import sensor_lines

    m, v = result.modes, result.video
    video_rows = {int(k): r for r, k in enumerate(v.mode_index)} if v is not None and len(v.surface_points_m) else {}
    placed = bool(result.sensors) and all(s.placed for s in result.sensors)
    if video_rows:
        pick, faces = surface_mesh(v.surface_points_m)
        points, lines = np.asarray(v.surface_points_m, float)[pick], []
        source = "video"
    elif placed:
        points = np.stack([s.position_m for s in result.sensors])
        dirs = np.stack([s.direction for s in result.sensors])
        faces, source = np.zeros((0, 3), int), "accelerometers"
        lines = [list(map(int, ln)) for ln in sensor_lines(np.arange(len(points)), points)]
    else:
        return None
    below = np.asarray(v.noise.below, bool) if video_rows and v.noise is not None else None
    modes = []
    for k in range(m.n_modes):
        if video_rows:
            if k not in video_rows:
                continue
            r = video_rows[k]
            shape = np.asarray(v.surface_residues[r], complex)[pick]
            judged = below is None or not bool(below[r])
        else:
            shape = np.asarray(m.shapes[k], complex)[:, None] * dirs
            judged = True
        shape = np.nan_to_num(shape)
        peak = float(np.linalg.norm(np.abs(shape), axis=1).max()) if len(shape) else 0.0
        shape = shape / peak if peak > 0 else shape
        modes.append({"mode": k + 1, "freq_hz": float(m.freq_hz[k]), "damping": float(m.damping[k]),
                      "source": source, "judged": judged,
                      "re": _rounded(shape.real), "im": _rounded(shape.imag)})
    if not modes:
        return None
    return {"kind": KIND, "schema": SCHEMA,
            "surface": {"points_m": _rounded(points), "faces": np.asarray(faces, int).tolist(), "lines": lines},
            "modes": modes}


def write_shapes(path: Path, result: AnalysisResult) -> bool:
    """plots/shapes3d.json (`shapes_document`); False where there is no shape to draw."""
    doc = shapes_document(result)
    if doc is None:
        return False
    atomic_write_text(path, json.dumps(doc, separators=(",", ":"), allow_nan=False) + "\n")
    log.info("3D shapes: %d modes on %d points, %d faces", len(doc["modes"]), len(doc["surface"]["points_m"]),
             len(doc["surface"]["faces"]))
    return True


def _array(value, shape_tail: tuple[int, ...], kind, what: str) -> np.ndarray:
    a = np.asarray(value, kind)
    if a.ndim != 1 + len(shape_tail) or a.shape[1:] != shape_tail or (kind is float and not np.isfinite(a).all()):
        raise ValueError(f"{what}: expected finite numbers of shape (n, {', '.join(map(str, shape_tail))})")
    return a


def parse_shapes(data: bytes) -> dict:
    """The file's contents (`write_shapes`) read back and checked, its one reader: {"points" (N, 3), "faces" (F, 3),
    "lines" (L, 2), "modes": {mode number: {"re", "im" (N, 3), "judged", "source"}}}, every number finite and every
    index in range. ValueError naming what is wrong (a hand edit, a file of another kind)."""
    try:
        raw = json.loads(data.decode("utf-8"))
        if not isinstance(raw, dict) or raw.get("kind") != KIND:
            raise ValueError(f"expected kind {KIND!r}")
        surface = raw["surface"]
        points = _array(surface["points_m"], (3,), float, "surface.points_m")
        n = len(points)
        faces = _array(surface["faces"] or np.zeros((0, 3)), (3,), int, "surface.faces")
        lines = _array(surface["lines"] or np.zeros((0, 2)), (2,), int, "surface.lines")
        for name, idx in (("faces", faces), ("lines", lines)):
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"surface.{name}: an index names no point")
        modes = {}
        for i, m in enumerate(raw["modes"]):
            re_, im_ = (_array(m[c], (3,), float, f"modes[{i}].{c}") for c in ("re", "im"))
            if len(re_) != n or len(im_) != n:
                raise ValueError(f"modes[{i}]: expected {n} points")
            modes[int(m["mode"])] = {"re": re_, "im": im_, "judged": bool(m["judged"]),
                                     "source": str(m.get("source", ""))}
    except (KeyError, TypeError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"not a 3D shapes file ({type(e).__name__}: {e})") from e
    except ValueError as e:      # numpy's, on a value that is no number; ours name the field already
        if str(e).startswith(("surface.", "modes[", "expected kind")):
            raise
        raise ValueError(f"not a 3D shapes file ({e})") from e
    return {"points": points, "faces": faces, "lines": lines, "modes": modes}


__all__ = ["KIND", "SCHEMA", "alpha_faces", "drop_floaters", "parse_shapes", "shapes_document", "write_shapes"]
