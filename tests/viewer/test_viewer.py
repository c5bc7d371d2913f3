"""The viewer on a small capture whose motion is hil_sim's exact one: the window driven offscreen (its sliders, its
mode list, clicks on the FRF plot), its images measured against that truth; the exports and the command line."""
from __future__ import annotations

import shutil
from dataclasses import replace

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image, ImageSequence

from odsplat.analysis import AnalyzeSettings, structure_mask
from odsplat.app.cli import main
from odsplat.app.viewer import default_state, load_viewer, render_view
from odsplat.app.viewer.app import ViewerWindow, alpha_to_slider
from odsplat.hil_sim.structure import ModalStructure
from odsplat.spine.mp4 import count_frames

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def data(captures):
    return load_viewer(captures[0])


@pytest.fixture(scope="module")
def window(data):
    w = ViewerWindow(data)
    w.show()
    w.app.processEvents()
    yield w
    w.window.close()


def _tip_time(data) -> float:
    """The time the structure's Gaussians move most."""
    sc = data.scene
    amp = np.linalg.norm(sc.displacement_m[:, sc.structure], axis=2).max(axis=1)
    return float(sc.times_s[int(np.argmax(amp))])


def _shift_px(a: np.ndarray, b: np.ndarray, box) -> float:
    """Sub-pixel translation of b against a inside box (x0, y0, x1, y1): phase correlation of the grey crops."""
    x0, y0, x1, y1 = box
    ga = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)[y0:y1, x0:x1].astype(np.float64)
    gb = cv2.cvtColor(b, cv2.COLOR_RGB2GRAY)[y0:y1, x0:x1].astype(np.float64)
    win = cv2.createHanningWindow(ga.shape[::-1], cv2.CV_64F)
    (dx, dy), _ = cv2.phaseCorrelate(ga, gb, win)
    return float(np.hypot(dx, dy))


def _tip_box(data, state, half_px: int = 40):
    """A box in the view's pixels around the arm's free end (the structure's Gaussian that moves most)."""
    from odsplat.app.viewer.draw import project
    from odsplat.app.viewer.model import camera_for

    sc = data.scene
    i = int(np.argmax(np.linalg.norm(sc.displacement_m, axis=2).max(axis=0)))
    uv, _ = project(camera_for(data, state), sc.means_m[i:i + 1].astype(float))
    u, v = (int(round(c)) for c in uv[0])
    return max(u - half_px, 0), max(v - half_px, 0), u + half_px, v + half_px


def test_the_structure_mask_is_the_analysis_rule_and_matches_the_truth(data, captures):
    _, floor, _ = captures
    assert np.array_equal(data.scene.structure, ~floor)
    assert "above the floor" in data.scene.structure_rule


def test_a_clump_of_gaussians_apart_from_the_structure_is_not_the_structure(captures):
    """The structure rule the analysis and the viewer's structure-only view share (`analysis.structure_mask`): a
    fit's stray clump beside the structure (20 Gaussians 5 cm off a 3000-point column) is left out, as one isolated
    point is; the column stays whole, and the floor goes by its own rule."""
    rng = np.random.default_rng(2)
    column = np.column_stack([rng.uniform(-0.02, 0.02, 3000), rng.uniform(-0.02, 0.02, 3000),
                              rng.uniform(0.02, 0.6, 3000)])
    clump = rng.normal([0.1, 0.0, 0.3], 0.003, (20, 3))
    floor = np.column_stack([rng.uniform(-0.3, 0.3, 200), rng.uniform(-0.3, 0.3, 200), np.zeros(200)])
    keep, rule = structure_mask(captures[0], np.concatenate([column, clump, floor]), AnalyzeSettings())
    assert keep[:3000].all() and not keep[3000:].any(), rule
    assert "20 left out: floaters" in rule, rule
    assert "floaters" not in structure_mask(captures[0], column, AnalyzeSettings())[1]


def test_modes_the_analysis_did_not_judge_are_grey_and_say_why(data, window, captures):
    """As in the report: the analysis's list of modes it did not judge (AnalysisDocument.not_judged) marks the same
    modes in the viewer's list, grey, with why in their label; a mode marked so carries its reason (a hand-set one
    here, where the capture's analysis judged every mode)."""
    from odsplat.analysis import read_analysis

    grey = read_analysis(captures[0]).not_judged()
    modes = [m for m in data.modes if m.kind == "mode"]
    assert [m.not_judged for m in modes] == [grey.get(k, "") for k in range(len(modes))]
    for k, m in enumerate(modes):
        colour = window.mode_list.item(k + 1).foreground().color()
        assert (colour.red(), colour.green(), colour.blue()) == ((140, 140, 140) if m.not_judged else (0, 0, 0)) \
            or not m.not_judged, (k, colour.name())
    below = replace(modes[0], not_judged="below the noise floor: not judged")
    assert below.label().endswith("(below the noise floor: not judged)") and "MAC" in below.label()


def test_magnification_slider_grows_the_motion_in_proportion(data, window):
    t = _tip_time(data)
    window.set_state(structure_only=True, show_cameras=False, show_sensors=False, time_s=data.scene.times_s[0])
    box = _tip_box(data, window.state)
    shifts = {}
    for alpha in (10.0, 100.0):
        window.alpha_slider.setValue(alpha_to_slider(alpha))
        assert window.state.alpha == pytest.approx(alpha, rel=0.02)
        window.set_time(data.scene.times_s[0])
        rest = window.image.copy()
        window.set_time(t)
        moved = window.image.copy()
        assert np.abs(moved.astype(int) - rest).max() > 10        # the image changes
        shifts[alpha] = _shift_px(rest, moved, box)
    assert shifts[10.0] > 0.2
    assert shifts[100.0] / shifts[10.0] == pytest.approx(10.0, rel=0.2)


def test_scrubbing_time_moves_the_structure_and_not_the_floor(data, window, captures):
    _, floor, _ = captures
    window.set_state(mode=None, alpha=100.0, structure_only=False, show_cameras=False, show_sensors=False)
    window.time_slider.setValue(0)
    assert window.state.time_s == pytest.approx(data.scene.times_s[0])
    rest = window.image.copy()
    t = _tip_time(data)
    t0, t1 = data.time_range_s
    window.time_slider.setValue(round(1000 * (t - t0) / (t1 - t0)))
    assert window.state.time_s == pytest.approx(t, abs=(t1 - t0) / 1000)
    moved = window.image.copy()
    assert window.time_cursor.value() == pytest.approx(1e3 * window.state.time_s)     # the plots' cursor follows
    # where the structure is (its own render) the image changes; on the floor's own pixels it does not
    only = render_view(data, replace(window.state, structure_only=True, time_s=t0), overlays=False)
    bg = render_view(data, replace(window.state, box_m=((9, 9, 9), (10, 10, 10))), overlays=False)
    on_structure = np.abs(only.astype(int) - bg).max(axis=2) > 8
    floor_only = render_view(data, replace(window.state, box_m=((-1, -1, -1), (1, 1, 0.005))), overlays=False)
    on_floor = (np.abs(floor_only.astype(int) - bg).max(axis=2) > 8) & ~on_structure
    on_floor[:30] = False                                         # the caption
    diff = np.abs(moved.astype(int) - rest).max(axis=2)
    assert diff[on_structure].mean() > 5 * max(diff[on_floor].mean(), 0.2)
    assert on_floor.sum() > 2000


def test_structure_only_removes_the_floors_pixels(data, window):
    window.set_state(mode=None, time_s=data.scene.times_s[0], alpha=1.0, show_cameras=False, show_sensors=False)
    window.structure_box.setChecked(False)
    full = window.image.copy()
    window.structure_box.setChecked(True)
    assert window.state.structure_only
    only = window.image.copy()
    st = replace(window.state, structure_only=False)
    bg = render_view(data, replace(st, box_m=((9, 9, 9), (10, 10, 10))))
    floor = render_view(data, replace(st, box_m=((-1, -1, -1), (1, 1, 0.005))), overlays=False)
    structure = render_view(data, replace(st, structure_only=True), overlays=False)
    bg0 = render_view(data, replace(st, box_m=((9, 9, 9), (10, 10, 10))), overlays=False)
    on_floor = (np.abs(floor.astype(int) - bg0).max(axis=2) > 8) & ~(np.abs(structure.astype(int) - bg0).max(
        axis=2) > 0)
    on_floor[:30] = False
    assert on_floor.sum() > 2000
    assert np.mean(np.abs(full.astype(int) - bg).max(axis=2)[on_floor] > 8) > 0.9     # the floor is drawn ...
    assert np.mean(np.abs(only.astype(int) - bg).max(axis=2)[on_floor] > 2) < 0.01    # ... and gone
    window.structure_box.setChecked(False)


def test_selecting_a_mode_shows_its_frequency_and_animates_at_it(data, window):
    truth = ModalStructure()
    window.set_state(structure_only=True, alpha=300.0, show_cameras=False, show_sensors=False)
    for k in (0, 2):
        window.mode_list.setCurrentRow(k + 1)
        m = data.modes[k]
        assert window.state.mode == k
        assert f"{m.freq_hz:.2f} Hz" in window.mode_label.text()
        assert m.freq_hz == pytest.approx(truth.freqs_hz[k], rel=0.01)
        period = 1.0 / m.freq_hz
        frames = []
        for phase in (0.0, 0.25, 0.5, 1.0):
            window.set_time(phase * period + 0.1 * period)
            frames.append(window.image.astype(int))
        d_quarter = np.abs(frames[1] - frames[0]).mean()
        d_half = np.abs(frames[2] - frames[0]).mean()
        d_period = np.abs(frames[3] - frames[0]).mean()
        assert d_half > 0.05 and d_quarter > 0.05
        assert d_period < 0.02 * d_half            # one period later it is the same image


def test_clicking_an_frf_peak_selects_the_nearest_mode(data, window):
    from PySide6 import QtCore
    from PySide6.QtTest import QTest

    for k in (1, 2, 0):
        f = data.modes[k].freq_hz
        pos = window.frf_click_position(1.03 * f)
        QTest.mouseClick(window.plots.viewport(), QtCore.Qt.MouseButton.LeftButton,
                         QtCore.Qt.KeyboardModifier.NoModifier, pos)
        window.app.processEvents()
        assert window.state.mode == k
        assert window.freq_cursor.value() == pytest.approx(f)
        assert f"{f:.2f} Hz" in window.mode_label.text()


def test_an_exported_mp4_has_the_requested_frames(data, window, tmp_path):
    window.set_state(mode=0, alpha=100.0)
    path = window.export(tmp_path / "mode1.mp4", n_frames=7, turntable=True)
    assert count_frames(path) == 7
    window.mode_list.setCurrentRow(0)
    path = window.export(tmp_path / "motion.gif", n_frames=5, turntable=False)
    frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(path))]
    assert len(frames) == 5 and np.abs(frames[0].astype(int) - frames[-1]).max() > 10


def test_snap_to_a_capture_camera_looks_through_it(data, window):
    from odsplat.app.viewer.model import camera_for

    window.camera_combo.setCurrentIndex(2)
    window.camera_combo.activated.emit(2)
    cam = camera_for(data, window.state)
    assert window.state.snap == 1
    assert np.allclose(cam.R, data.cameras[1].R) and np.allclose(cam.t, data.cameras[1].t)
    window.compare_box.setChecked(True)
    assert window.real.pixmap() is not None and not window.real.pixmap().isNull()
    window.view.on_orbit(10, 0)
    assert window.state.snap is None
    window.compare_box.setChecked(False)


def test_the_command_line_exports_and_refuses_bad_input(captures, tmp_path):
    cap = captures[0]
    gif = tmp_path / "v.gif"
    res = CliRunner().invoke(main, ["view", str(cap.root), "--export", str(gif), "--frames", "4", "--mode", "1",
                                    "--size", "160", "120"])
    assert res.exit_code == 0, res.output
    assert Image.open(gif).n_frames == 4
    res = CliRunner().invoke(main, ["view", str(cap.root), "--export", str(gif), "--frames", "3", "--ods", "2",
                                    "--size", "160", "120"])
    assert res.exit_code == 0 and Image.open(gif).n_frames == 3, res.output
    png = tmp_path / "v.png"
    res = CliRunner().invoke(main, ["view", str(cap.root), "--screenshot", str(png), "--structure-only"])
    assert res.exit_code == 0, res.output
    assert Image.open(png).size == (640, 480)
    for args, text in (([str(tmp_path / "nothing")], "no such capture"),
                       ([str(cap.root), "--mode", "9", "--screenshot", str(png)], "--mode"),
                       ([str(cap.root), "--ods", "3", "--screenshot", str(png)],
                        "--ods: expected an ODS line from 1 to 2"),
                       ([str(cap.root), "--ods", "1", "--mode", "1", "--screenshot", str(png)], "give one of"),
                       ([str(cap.root), "--alpha", "0", "--screenshot", str(png)], "--alpha"),
                       ([str(cap.root), "--export", str(tmp_path / "v.avi")], ".mp4 or .gif")):
        res = CliRunner().invoke(main, ["view", *args])
        assert res.exit_code == 2 and text in res.output and "Traceback" not in res.output, res.output
    bare = tmp_path / "bare"
    shutil.copytree(cap.root, bare, ignore=shutil.ignore_patterns("analysis"))
    res = CliRunner().invoke(main, ["view", str(bare), "--screenshot", str(png)])
    assert res.exit_code == 2 and "no analysis" in res.output, res.output


def test_without_a_reconstruction_the_sensors_shapes_are_animated(captures):
    acc = load_viewer(captures[2])
    assert acc.scene is None and acc.modes and all(m.sensors_accel is not None for m in acc.modes)
    assert any("no reconstruction" in n for n in acc.notes)
    w = ViewerWindow(acc)
    try:
        assert w.state.mode == 0 and "Hz" in w.mode_label.text()
        w.set_state(alpha=1000.0, show_cameras=False)
        period = 1 / acc.modes[0].freq_hz
        images = []
        for phase in (0.0, 0.5, 1.0):
            w.set_time(phase * period)
            images.append(w.image.astype(int))
        assert np.abs(images[1] - images[0]).max() > 50
        assert np.abs(images[2] - images[0]).max() < 5
        assert len(w.frf_plot.listDataItems()) == len(acc.frf_names) == len(acc.sensors) > 0
        assert len(w.force_plot.listDataItems()) == 1
        # each FRF and acceleration named in a legend (issue 46: the FRFs had none)
        names = [label.text for _, label in w.frf_legend.items]
        assert len(names) == len(acc.sensors) and all(s.name in " ".join(names) for s in acc.sensors), names
        assert len(w.accel_legend.items) == len(acc.sensors)
    finally:
        w.window.close()


def test_the_default_view_shows_the_recorded_motion_at_its_largest_after_the_impact(data):
    """A screenshot by default was taken at the first timestep, before the impact, where nothing moves (issue 46)."""
    state = default_state(data)
    sc = data.scene
    assert state.mode is None and state.time_s >= 0
    rms = np.sqrt(np.mean(np.sum(sc.displacement_m[:, sc.structure].astype(float) ** 2, axis=2), axis=1))
    k = int(np.argmin(np.abs(sc.times_s - state.time_s)))
    assert rms[k] == pytest.approx(rms[sc.times_s >= 0].max())


def _pixels(cam, points_m: np.ndarray) -> np.ndarray:
    c = points_m @ np.asarray(cam.R, float).T + np.asarray(cam.t, float)
    return (c @ np.asarray(cam.K, float).T)[:, :2] / c[:, 2:3]


def test_a_mode_at_the_default_magnification_moves_the_structure_visibly(data):
    """At x100 a mode barely moved on the demo (issue 46): by default the magnification moves the structure's
    largest motion 5 % of its size, at least 5 px on screen at the default view."""
    from odsplat.app.display import ViewSettings, view_state
    from odsplat.app.viewer.model import camera_for, motion_at

    modes = [k for k, m in enumerate(data.modes) if m.kind == "mode" and m.gaussians is not None]
    assert modes
    sc = data.scene
    for k in modes:
        state = view_state(data, ViewSettings(mode=data.modes[k].number))
        assert state.mode == k and state.alpha != 100.0
        cam = camera_for(data, state)
        disp, _ = motion_at(data, state)
        rest = sc.means_m[sc.structure].astype(float)
        moved = rest + state.alpha * disp[sc.structure].astype(float)
        shift = np.linalg.norm(_pixels(cam, moved) - _pixels(cam, rest), axis=1)
        assert np.percentile(shift, 99) >= 5.0, (k, state.alpha, np.percentile(shift, 99))
    # the measured motion too, at its largest after the impact
    state = view_state(data, ViewSettings(motion=True))
    assert state.time_s >= 0 and state.alpha > 1


def test_the_structure_drawn_as_its_surface_moves_with_a_mode(data):
    """--surface (issue 46: a surface, not dots): the structure as the triangles of `analysis.surface_mesh` over the
    analysis's surface points, the report's 3D surface, where the Gaussians show it; half a cycle of a mode at the
    default magnification moves what is drawn by at least 5 px where the structure moves most."""
    from scipy import ndimage

    from odsplat.app.display import ViewSettings, view_state

    assert data.surface is not None and len(data.surface.faces) >= 20
    m = next(m for m in data.modes if m.kind == "mode" and m.surface is not None)
    state = view_state(data, ViewSettings(mode=m.number, structure_only=True, surface=True, colour="displacement"))
    drawn = (render_view(data, state, overlays=False) < 250).any(axis=2)        # white around the structure
    later = render_view(data, replace(state, time_s=state.time_s + 0.5 / m.freq_hz), overlays=False)
    changed = (later < 250).any(axis=2) ^ drawn             # the pixels the outline left and entered
    assert 2 * ndimage.distance_transform_edt(changed).max() >= 5.0
    gauss = (render_view(data, replace(state, surface=False), overlays=False) < 250).any(axis=2)
    assert (gauss & drawn).sum() >= 0.5 * drawn.sum()


def test_the_surface_is_drawn_solid(data):
    """Drawn over dense surface points (a column's four faces every 10 mm, each point 1 mm off, as Gaussians lie),
    the triangles cover their outline with no hole (the drawn pixels fill their own outline within 0.5 %): the
    painter's order and the alpha shape leave no gap."""
    from scipy import ndimage

    from odsplat.analysis import surface_mesh
    from odsplat.app.viewer.model import Surface

    g = np.arange(-0.04, 0.04, 0.01)                    # each face stops a step short of the next: no corner twice
    a, b = (v.ravel() for v in np.meshgrid(g, np.arange(0.1, 0.5, 0.01)))
    faces4 = [np.column_stack([np.full(a.size, -0.04), a, b]), np.column_stack([np.full(a.size, 0.04), -a, b]),
              np.column_stack([-a, np.full(a.size, -0.04), b]), np.column_stack([a, np.full(a.size, 0.04), b])]
    points = np.concatenate(faces4) + np.random.default_rng(4).normal(0, 0.001, (4 * a.size, 3))
    pick, faces = surface_mesh(points)
    assert len(faces) > 100
    surface = Surface(points[pick], faces, np.zeros(len(pick), int))
    modes = tuple(replace(m, surface=np.zeros((len(pick), 3), complex)) for m in data.modes)
    box = replace(data, surface=surface, modes=modes)
    state = replace(default_state(box, structure_only=True, colour="displacement", surface=True), mode=0,
                    show_cameras=False, show_sensors=False)
    drawn = (render_view(box, state, overlays=False) < 250).any(axis=2)
    holes = ndimage.binary_fill_holes(drawn) & ~drawn
    assert drawn.sum() > 2000 and holes.sum() <= 0.005 * drawn.sum(), (drawn.sum(), holes.sum())


def test_default_state_without_reconstruction_selects_a_mode(captures):
    acc = load_viewer(captures[2])
    img = render_view(acc, default_state(acc))
    assert img.shape == (480, 640, 3) and (img < 250).any()


def test_dragging_the_view_orbits_the_camera(data, window):
    from PySide6 import QtCore
    from PySide6.QtTest import QTest

    window.set_state(snap=None, mode=None, structure_only=False)
    before, azimuth = window.image.copy(), window.state.orbit.azimuth_deg
    centre = window.view.rect().center()
    left, none = QtCore.Qt.MouseButton.LeftButton, QtCore.Qt.KeyboardModifier.NoModifier
    QTest.mousePress(window.view, left, none, centre)
    for k in range(1, 6):
        QTest.mouseMove(window.view, centre + QtCore.QPoint(10 * k, 0))
        window.app.processEvents()
    QTest.mouseRelease(window.view, left, none, centre + QtCore.QPoint(50, 0))
    window.app.processEvents()
    assert window.state.orbit.azimuth_deg == pytest.approx((azimuth - 0.4 * 50) % 360)
    assert window.image.shape == before.shape and np.abs(window.image.astype(int) - before).mean() > 1


def test_playback_runs_at_the_speed_asked_and_loops(data, window):
    window.set_state(mode=None, time_s=data.time_range_s[0])
    window.speed_box.setValue(2.0)                       # 2 ms of test per second
    window.advance(1.5)
    assert window.state.time_s == pytest.approx(data.time_range_s[0] + 3e-3)
    t0, t1 = data.time_range_s
    window.set_time(t1 - 1e-3)
    window.loop_box.setChecked(True)
    window.advance(1.0)                                  # 1 ms past the end: back to 1 ms after the start
    assert window.state.time_s == pytest.approx(t0 + 1e-3)
    window.speed_box.setValue(1.0)
    # a mode plays one cycle in 1.5 s whatever its frequency (at 1 ms of test per second 23.5 Hz took 42 s)
    from odsplat.app.viewer.app import MODE_CYCLE_S
    f = data.modes[0].freq_hz
    window.set_state(mode=0, time_s=0.0)
    window.advance(0.5 * MODE_CYCLE_S)
    assert window.state.time_s == pytest.approx(0.5 / f)
    window.set_state(mode=None, time_s=t0)


def test_the_dragged_box_and_the_colour_scale(data, window):
    from odsplat.app.viewer.model import colour_scale, visible

    window.set_state(mode=None, structure_only=False, box_m=None)
    sc = data.scene
    lo, hi = sc.means_m[sc.structure].min(axis=0), sc.means_m[sc.structure].max(axis=0)
    window.box_roi.setPos((float(lo[0]) - 0.01, float(lo[1]) - 0.01))
    window.box_roi.setSize((float(hi[0] - lo[0]) + 0.02, float(hi[1] - lo[1]) + 0.02))
    window.z_lo.setValue(0.02)
    window.use_box.setChecked(True)
    (bx0, by0, bz0), (bx1, by1, _) = window.state.box_m
    assert bx0 == pytest.approx(lo[0] - 0.01, abs=1e-6) and by1 == pytest.approx(hi[1] + 0.01, abs=1e-6)
    assert bz0 == pytest.approx(0.02)
    keep = visible(data, window.state)
    assert keep.sum() < sc.n and not keep[~sc.structure].any()     # the floor is below the box's z range
    window.use_box.setChecked(False)
    assert window.state.box_m is None
    window.colour_combo.setCurrentIndex(1)
    assert window.state.colour == "displacement"
    top, unit = colour_scale(data, window.state)
    assert unit == "m" and top == pytest.approx(np.percentile(np.linalg.norm(
        sc.displacement_m[:, sc.structure], axis=2), 99.5))
    window.select_mode(0)
    assert colour_scale(data, window.state)[1] == "m/N"
    bar = window.image[45:-45, -26:-18].astype(float)               # the colour bar: yellow top, dark blue foot
    top_rgb, foot_rgb = bar[:5].mean(axis=(0, 1)), bar[-5:].mean(axis=(0, 1))
    assert top_rgb[1] > 200 and top_rgb[2] < 100 and foot_rgb[2] > 100 and foot_rgb[1] < 50
    window.colour_combo.setCurrentIndex(0)


def test_an_ods_line_is_listed_animated_at_its_frequency_and_read_per_newton(data, window):
    """The analysis's ODS lines (here 23.5 Hz and 60 Hz, between two modes) follow the modes in the list; one turns
    at its own frequency, as the response to 1 N of harmonic force; its shapes are the analysis's; an FRF click
    still picks a mode."""
    lines = [m for m in data.modes if m.kind == "ods"]
    assert [round(m.freq_hz, 2) for m in lines] == [23.5, 60.0]
    n_modes = len(data.modes) - len(lines)
    line = lines[1]
    assert line.label().startswith("ODS line 2: 60.00 Hz (1 N harmonic)")
    # the accelerometers' ODS at the sensors, read along their directions, is the analysis's (results.h5)
    from odsplat.analysis import read_results_h5

    back = read_results_h5(data.capture.paths.analysis_dir / "results.h5")
    rec = {sh.name: sh for sh in back.shapes}["accelerometer ODS 60.00 Hz"]
    dirs = np.array([sn.direction for sn in data.sensors])
    np.testing.assert_allclose(line.sensors_accel, np.einsum("sc,sc->s", rec.values, dirs), rtol=1e-12)
    assert line.sensors_video is not None and line.gaussians is not None
    # 24 timesteps cannot separate 23.5 and 31 Hz: the analysis says the video's ODS at 23.5 Hz is their noise
    from odsplat.analysis import read_analysis

    notes = read_analysis(data.capture).notes
    assert any(n.startswith("ODS line 1 (23.5 Hz): the video's ODS there is carried by modes below") for n in notes), \
        notes
    window.set_state(structure_only=True, alpha=1000.0, show_cameras=False, show_sensors=False)
    window.mode_list.setCurrentRow(n_modes + 2)
    assert window.state.mode == n_modes + 1 and "60.00 Hz" in window.mode_label.text()
    period = 1.0 / 60.0
    frames = []
    for phase in (0.1, 0.6, 1.1):
        window.set_time(phase * period)
        frames.append(window.image.astype(int))
    d_half, d_period = np.abs(frames[1] - frames[0]).mean(), np.abs(frames[2] - frames[0]).mean()
    assert d_half > 0.05 and d_period < 0.02 * d_half
    assert data.mode_nearest(60.0) < n_modes                  # a click on the FRF selects modes only
    # the sensors' arrows move as the structure does: per newton for an ODS line, 2 |A| J for a mode (they once
    # took a mode's gain for every line, 2 J times too far)
    from odsplat.app.viewer.model import sensor_shifts_m

    state = replace(window.state, time_s=0.0)
    np.testing.assert_allclose(sensor_shifts_m(data, state), np.real(line.sensors_accel), rtol=1e-12)
    mode = replace(state, mode=0)
    np.testing.assert_allclose(sensor_shifts_m(data, mode),
                               2 * data.impulse_n_s * np.real(data.modes[0].sensors_accel), rtol=1e-12)
    assert not sensor_shifts_m(data, replace(state, mode=None)).any()
    window.mode_list.setCurrentRow(0)
