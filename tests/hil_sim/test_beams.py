"""The beam finite-element model (hil_sim.beams) against closed forms and its own matrices, and the two rigs built on
it, "frame" and "mast": their modes as designed, their sensors and hammer seeing every mode, their scenes in every
planned view with tags found, and `odsplat capture --sim --structure` running on them."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from click.testing import CliRunner

from odsplat.acquisition.plan import PlanSettings, plan_views, view_eye_m
from odsplat.app.cli import main
from odsplat.hil_sim.beams import (
    ALUMINIUM,
    STEEL,
    BeamStructure,
    FrameModel,
    Member,
    frame_structure,
    mast_structure,
    torsion_constant,
)
from odsplat.hil_sim.render import PinholeCamera, render
from odsplat.hil_sim.rig import HAMMER, make_rig
from odsplat.hil_sim.scene import STRUCTURE, STRUCTURE_TAG
from odsplat.hil_sim.structure import STRUCTURES, make_structure
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.spine.tags import detect_tags

NEW = ("frame", "mast")


def _cantilever(material, n_elements: int = 10) -> tuple[FrameModel, float, float, float]:
    length, bx, by = 0.6, 0.02, 0.03
    member = Member("bar", (0.0, 0.0, 0.0), (0.0, 0.0, length), (bx, by), material, n_elements)
    return FrameModel([member], [(0.0, 0.0, 0.0)]), length, bx, by


@pytest.mark.parametrize("material", [STEEL, ALUMINIUM], ids=lambda m: m.name)
def test_a_cantilever_has_the_closed_form_frequencies(material):
    model, length, bx, by = _cantilever(material)
    found = model.solve(6).freqs_hz
    e, rho, area = material.youngs_modulus_pa, material.density_kg_m3, bx * by
    bending = []
    for inertia in (by * bx**3 / 12, bx * by**3 / 12):         # thin along x bends first
        c = np.sqrt(e * inertia / (rho * area * length**4)) / (2 * np.pi)
        bending += [beta**2 * c for beta in (1.875104069, 4.694091133, 7.854757438)]
    # Clamped-free torsion, a quarter wave: f = sqrt(G J / (rho I_p)) / (4 L).
    ip = area * (bx**2 + by**2) / 12
    torsion = np.sqrt(material.shear_modulus_pa * torsion_constant(bx, by) / (rho * ip)) / (4 * length)
    expected = np.sort([*bending, torsion])[:6]                # x1, y1, x2, y2, x3, torsion (axial: far above)
    err = np.abs(found - expected) / expected
    assert err.max() < 0.005, (found, expected)
    # measured with 10 elements: bending 8.5e-7 (first pair), 3.3e-5 (second pair), torsion 1.0e-3 (linear twist)
    assert err[:4].max() < 1e-4 and err[5] < 2e-3
    # J of a square: 0.1406 a^4 (Timoshenko & Goodier), of a 2:1 rectangle 0.229 a b^3
    assert torsion_constant(0.01, 0.01) == pytest.approx(0.1406e-8, rel=1e-3)
    assert torsion_constant(0.02, 0.01) == pytest.approx(0.2287 * 0.02 * 0.01**3, rel=1e-3)


@pytest.mark.parametrize("name", NEW)
def test_modes_are_mass_orthonormal_and_the_shapes_interpolate_the_nodes(name):
    st = make_structure(name)
    model, vec = st.model, st.vectors
    f = model.free
    phi = vec[f]
    np.testing.assert_allclose(phi.T @ model.mass[np.ix_(f, f)] @ phi, np.eye(st.n_modes), atol=1e-9)
    w2 = (2 * np.pi * st.freqs_hz) ** 2
    np.testing.assert_allclose(phi.T @ model.stiffness[np.ix_(f, f)] @ phi, np.diag(w2), atol=1e-6 * w2.max())
    # At the nodes (on the members' axes) the shapes are the eigenvectors' translations; clamped nodes stay put.
    nodal = vec.reshape(-1, 6, st.n_modes)
    at_nodes = st.mode_shapes(model.nodes_m)
    np.testing.assert_allclose(at_nodes, nodal[:, :3].transpose(0, 2, 1), atol=1e-12)
    assert np.abs(at_nodes[model.clamped]).max() == 0
    # Off the axis, a section moves rigidly: u = u_node + theta_node x r, at a node not owned by another member.
    member = st.geometry.members[-1]
    node = model.member_nodes[-1][member.n_elements // 2]
    lo, hi = member.box()
    corner = np.where(np.arange(3) == member.axis, model.nodes_m[node], hi)
    rigid = nodal[node, :3].T + np.cross(nodal[node, 3:].T, corner - model.nodes_m[node])
    np.testing.assert_allclose(st.mode_shapes(corner[None])[0], rigid, atol=1e-12)
    # Zero off the members: on the bolted-down blocks and in the air.
    blocks = np.array([0.5 * (np.asarray(lo_) + np.asarray(hi_)) for _, lo_, hi_ in st.geometry.blocks])
    assert np.abs(st.mode_shapes(np.vstack([blocks, [[1.0, 1.0, 1.0]]]))).max() == 0


@pytest.mark.parametrize("name", NEW)
def test_the_mesh_has_converged(name):
    st = make_structure(name)
    geo = st.geometry
    finer = dataclasses.replace(geo, members=tuple(dataclasses.replace(m, n_elements=2 * m.n_elements)
                                                   for m in geo.members))
    fine = BeamStructure(name, finer, st.mode_names, st.damping_ratios)
    change = np.abs(fine.freqs_hz / st.freqs_hz - 1)
    assert change.max() < 0.005                                # measured: < 2e-5
    assert change.max() < 1e-4, change


def _at(st, point) -> np.ndarray:
    return st.mode_shapes(np.asarray(point, float)[None])[0]    # (n_modes, 3)


def test_the_frame_has_its_designed_modes():
    st = frame_structure()
    f = st.freqs_hz
    assert st.n_modes == 5 and f[0] >= 15 and f[-1] < 400 and np.all(np.diff(f) > 0.2 * f[:-1]), f
    np.testing.assert_allclose(f, [37.43, 61.83, 96.01, 239.47, 329.53], rtol=1e-3)
    assert np.all((st.dampings >= 0.005) & (st.dampings <= 0.025))
    mid, top0, top1, tip = _at(st, (0.2, 0, 0.6)), _at(st, (-0.02, 0, 0.6)), _at(st, (0.42, 0, 0.6)), \
        _at(st, (0.2, 0.15, 0.6))
    # 1: sway out of plane: the beam moves along y as a whole, the stub's tip dips as the beam twists
    assert abs(mid[0, 1]) > 10 * max(abs(mid[0, 0]), abs(mid[0, 2])) and abs(tip[0, 2]) > 0.2 * abs(tip[0, 1])
    # 2: sway along the beam
    assert abs(mid[1, 0]) > 10 * np.abs(mid[1, 1:]).max() and top0[1, 0] == pytest.approx(top1[1, 0], rel=0.01)
    # 3: torsion about the vertical: the column tops move opposite along y, the stub's tip along x
    assert top0[2, 1] == pytest.approx(-top1[2, 1], rel=0.01) and abs(mid[2, 1]) < 0.01 * abs(top0[2, 1])
    assert abs(tip[2, 0]) > 0.5 * abs(top0[2, 1])
    # 4: the beam bends vertically (mid-span up, its ends hardly)
    assert abs(mid[3, 2]) > 20 * abs(top0[3, 2]) and abs(mid[3, 2]) > 10 * np.abs(mid[3, :2]).max()
    # 5: the columns' second out-of-plane bending: half-way up a column moves more along y than its top
    half = _at(st, (-0.02, 0, 0.345))
    assert abs(half[4, 1]) > 2 * abs(top0[4, 1])


def test_the_mast_has_closely_spaced_bending_pairs():
    st = mast_structure()
    f = st.freqs_hz
    np.testing.assert_allclose(f, [40.84, 42.10, 255.94, 263.85], rtol=1e-3)
    assert 0.01 < f[1] / f[0] - 1 < 0.05 and 0.01 < f[3] / f[2] - 1 < 0.05     # within 5 %: 3.1 % (20 / 19.4)
    assert f[0] >= 15 and f[3] < 400
    tip, low = _at(st, (0.2, 0, 0.72)), _at(st, (0.2, 0, 0.40))
    for k, axis in enumerate((0, 1, 0, 1)):                                  # x, y, x, y
        assert abs(tip[k, axis]) > 100 * np.abs(np.delete(tip[k], axis)).max()
    # second bending: a node between, so half-way up moves opposite to the tip
    assert np.all(np.sign(low[[2, 3], [0, 1]]) != np.sign(tip[[2, 3], [0, 1]]))
    assert np.all(np.sign(low[[0, 1], [0, 1]]) == np.sign(tip[[0, 1], [0, 1]]))


def _on_a_face(point, direction, boxes) -> bool:
    """The point lies on a face of one of the boxes whose outward normal is `direction`."""
    p, d = np.asarray(point, float), np.asarray(direction, float)
    axis = int(np.argmax(np.abs(d)))
    for lo, hi in boxes.values():
        face = hi[axis] if d[axis] > 0 else lo[axis]
        if np.all((p >= lo - 1e-9) & (p <= hi + 1e-9)) and abs(p[axis] - face) < 1e-9:
            return True
    return False


@pytest.mark.parametrize("name", NEW)
def test_every_mode_moves_a_sensor_and_is_excited_by_the_hammer(name):
    rig = make_rig(name)
    st, cfg = rig.structure, rig.config
    boxes = st.geometry.boxes()
    # the largest motion of each mode anywhere on the structure's surface
    largest = np.linalg.norm(rig.scene.shapes[rig.scene.structure_vertices()], axis=2).max(axis=0)
    assert len(cfg.accelerometers) == 4 and len(cfg.can_nodes) == 2
    seen = []
    for a in cfg.accelerometers:
        d = np.asarray(a.direction)
        assert a.name.startswith("acc_") and np.count_nonzero(d) == 1 and _on_a_face(a.point_m, d, boxes), a
        seen.append(np.abs(st.participation(a.point_m, d)) / largest)
    best = np.max(seen, axis=0)
    assert best.min() >= 0.4, best                          # the rule asks 20 %; measured: frame 43 %, mast 92 %
    for n in cfg.can_nodes:
        assert np.linalg.norm(_at(st, n.point_m), axis=1).min() > 0.1 * largest.min(), n
    point, direction = HAMMER[name]
    assert rig.hammer.point_m == point
    gamma = np.abs(st.participation(point, rig.hammer.direction))
    assert gamma.min() >= 0.3 * gamma.max(), gamma          # the rule asks 10 %; measured: frame 41 %, mast 54 %
    # the hammer's point is on an edge of a member, its direction into the bar
    owner = st.model.owner(np.asarray(point)[None], tol_m=1e-9)[0]
    assert owner >= 0
    lo, hi = st.geometry.members[owner].box()
    on = np.isclose(point, lo) | np.isclose(point, hi)
    inward = np.where(np.isclose(point, lo), 1.0, -1.0) * np.asarray(rig.hammer.direction)
    assert on.sum() >= 2 and np.all(inward[on] > 0)


@pytest.mark.parametrize("name", NEW)
def test_the_rig_is_in_every_planned_view_and_shows_its_tags(name, tmp_path):
    rig = make_rig(name)
    boxes = rig.structure.geometry.boxes()
    corners = np.array([[(lo, hi)[i][0], (lo, hi)[j][1], (lo, hi)[k][2]] for lo, hi in boxes.values()
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    views = plan_views(PlanSettings())
    tags_seen = []
    for v in views:
        cam = PinholeCamera.look_at(view_eye_m(v), v.target_m, fov_deg=50, width_px=400, height_px=300)
        px, _ = cam.project(corners)
        assert np.all((px >= 0) & (px <= (400, 300))), v                    # all of it in the frame
        out = render(rig.scene.mesh(), cam, rig.scene.atlas, background=0.5)
        covered = int(np.sum(out.object_id == STRUCTURE))
        assert 1000 < covered < 0.1 * 400 * 300, (v, covered)              # little of the image: 1.4 to 4.7 %
        found = {d.id for d in detect_tags((np.clip(out.image, 0, 1) * 255).astype(np.uint8))}
        assert len(found - {100, 101}) >= 2, (v, found)                   # floor tags, some behind the rig
        tags_seen.append(found & {100, 101})
        if v.index == 20:
            assert np.any(out.object_id == STRUCTURE_TAG) and tags_seen[-1] == {100}, found
    # each structure tag is found in some views (frame: 9 of 27, mast: 12)
    assert sum(100 in t for t in tags_seen) >= 3 and sum(101 in t for t in tags_seen) >= 3
    # the structure's tags are on its bolted-down blocks: they do not move
    tag_vertices = np.unique(rig.scene.faces[rig.scene.object_id == STRUCTURE_TAG])
    assert np.abs(rig.scene.shapes[tag_vertices]).max() == 0


@pytest.mark.parametrize("name", NEW)
def test_a_short_simulated_capture_of_the_rig(name, tmp_path):
    assert name in STRUCTURES
    out = tmp_path / name
    r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", "--structure", name,
                                  "--views", "3", "--frames", "12", "--pretrigger-frames", "4"])
    assert r.exit_code == 0, r.output
    cap = Capture.open(out)
    assert len(cap.manifest.takes) == 3
    truth = np.load(cap.root / "takes" / f"{cap.manifest.takes[0].name}.truth.npz")
    assert str(truth["structure"]) == name
    np.testing.assert_allclose(truth["freqs_hz"], make_structure(name).freqs_hz)


def test_bad_members_and_names_are_refused():
    for make, where in [(lambda: Member("m", (0, 0, 0), (0.1, 0.1, 0), (0.01, 0.01)), "Member 'm'"),
                        (lambda: Member("m", (0, 0, 1), (0, 0, 0), (0.01, 0.01)), "Member 'm'"),
                        (lambda: FrameModel([Member("m", (0, 0, 0), (0, 0, 1), (0.01, 0.01))], [(0, 0, 0.55)]),
                         "FrameModel.clamped_m"),
                        (lambda: make_structure("truss"), "structure"),
                        # a stub meeting a beam between two of its nodes is not joined to it
                        (lambda: FrameModel([Member("beam", (0, 0, 1), (0, 0, 2), (0.01, 0.01), n_elements=3),
                                             Member("stub", (0, 0, 1.5), (0.2, 0, 1.5), (0.01, 0.01))], [(0, 0, 1)]),
                         "FrameModel.members")]:
        with pytest.raises(InputError) as e:
            make()
        assert where in str(e.value) and "\n" not in str(e.value)
