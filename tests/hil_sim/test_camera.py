"""The simulated camera: triggers, pretrigger ring buffer, counters, strobe, drops, drift, image options."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.acquisition.camera import CameraDriver, CameraTimeout, TriggerSettings
from odsplat.hil_sim.camera import SimCamera, SimCameraConfig
from odsplat.hil_sim.render import PinholeCamera
from odsplat.hil_sim.scene import STRUCTURE, build_scene
from odsplat.hil_sim.structure import Impact
from odsplat.spine.errors import InputError, OdsplatError

TIP = (0.45, 0.0, 0.60)


@pytest.fixture(scope="module")
def view():
    return PinholeCamera.look_at((1.0, -1.1, 0.9), (0.15, 0.0, 0.35), fov_deg=45, width_px=96, height_px=80)


def _motion(scene, peak_n=200.0):
    impacts = [Impact(0.01, TIP, (0.0, 0.0, -1.0), peak_n)]
    return lambda t: scene.structure.modal_response(impacts, t).q


def _camera(scene, view, **kw):
    config = kw.pop("config", SimCameraConfig(fps=1000.0, shot_noise=False, read_noise_e=0.0))
    return SimCamera(scene, view, _motion(scene), config, **kw)


@pytest.mark.parametrize("mode,first,last", [("start", 0, 99), ("center", -50, 49), ("end", -99, 0)])
def test_pretrigger_modes(scene, view, mode, first, last):
    cam = _camera(scene, view)
    cam.arm(n_frames=100, pretrigger=mode, at_s=0.0)
    rec = cam.trigger_at(0.1234)
    assert (rec.counters[0], rec.counters[-1], len(rec.counters)) == (first, last, 100)
    # Frame 0 is the first exposure that starts at or after the edge.
    assert rec.trigger_frame_time_s == pytest.approx(0.124)
    np.testing.assert_allclose(np.diff(rec.exposure_start_s), 1e-3)


def test_ring_buffer_holds_only_what_was_exposed_since_the_arm(scene, view):
    cam = _camera(scene, view)
    cam.arm(n_frames=100, pretrigger="end", at_s=0.1)
    rec = cam.trigger_at(0.1051)
    assert rec.pretrigger_requested == 99 and rec.pretrigger_available == 6
    assert rec.counters[0] == -6 and len(rec.counters) == 7


def test_internal_trigger_starts_at_the_arm(scene, view):
    cam = _camera(scene, view)
    cam.arm(n_frames=10, trigger="internal", at_s=0.0202)
    assert cam.recording.counters.tolist() == list(range(10))
    assert cam.recording.exposure_start_s[0] == pytest.approx(0.021)
    with pytest.raises(OdsplatError, match="internal"):
        cam.trigger_at(0.03)


def test_dropped_frames_skip_counters_but_still_strobe(scene, view):
    cam = _camera(scene, view, drop_counters=(3, 7))
    cam.arm(n_frames=10, at_s=0.0)
    rec = cam.trigger_at(0.0)
    assert rec.counters.tolist() == [0, 1, 2, 4, 5, 6, 8, 9] and rec.dropped.tolist() == [3, 7]
    fs = 100_000.0
    t = np.arange(0, 0.012, 1 / fs)
    ttl = cam.ttl(t)
    rises = t[1:][np.diff((ttl > 2.5).astype(int)) == 1]
    # Every exposure strobes, the dropped ones included, and the strobe stops after the take.
    np.testing.assert_allclose(rises, np.arange(1, 10) * 1e-3, atol=1 / fs)
    assert ttl[t > 0.0096].max() == 0 and ttl[(t >= 0.003) & (t < 0.0005 + 0.003)].min() == 5.0


def test_clock_drift_and_offset(scene, view):
    cam = _camera(scene, view, clock_offset_s=2.5e-4, clock_drift_ppm=200.0)
    cam.arm(n_frames=50, at_s=0.0)
    rec = cam.trigger_at(0.01)
    assert np.diff(rec.exposure_start_s).mean() == pytest.approx(1e-3 / (1 + 2e-4), rel=1e-9)
    assert rec.trigger_frame_time_s == pytest.approx(2.5e-4 + 10 / (1000 * (1 + 2e-4)))


def test_images_move_with_the_structure(scene, view):
    cam = _camera(scene, view)
    cam.arm(n_frames=3, pretrigger=1, at_s=0.0)
    cam.trigger_at(0.0105)
    frames = list(cam.frames())
    assert [f.counter for f in frames] == [-1, 0, 1]
    assert [f.time_s for f in frames] == [-1e-3, 0.0, 1e-3]  # the camera's own clock
    before, after = frames[0].image, frames[2].image
    assert before.dtype == np.uint16 and before.shape == (80, 96) and before.max() <= 4095
    starts = cam.recording.exposure_start_s
    on = cam.truth(starts[0]).object_id == STRUCTURE
    assert np.abs(after.astype(int) - before.astype(int))[on].mean() > 1.0
    # alpha multiplies the motion: the natively magnified truth differs from the true image.
    t = starts[2]
    true, magnified = cam.truth(t).image, cam.truth(t, alpha=20.0).image
    assert np.abs(magnified - true)[on].mean() > 1e-2


def test_exposure_blur_is_the_mean_over_the_exposure(scene, view):
    config = SimCameraConfig(fps=1000.0, exposure_s=8e-4, blur_samples=4, shot_noise=False, read_noise_e=0.0)
    cam = _camera(scene, view, config=config)
    sharp = SimCamera(scene, view, cam.motion, SimCameraConfig(fps=1000.0, exposure_s=8e-4))
    t0 = 0.012
    # A one-sample render looks at the middle of its exposure: shift it to each quarter's middle.
    parts = [sharp.radiance(t0 + (k + 0.5) * 2e-4 - 4e-4) for k in range(4)]
    np.testing.assert_allclose(cam.radiance(t0), np.mean(parts, axis=0), atol=1e-6)


def test_image_formats_and_noise(view):
    rgb_scene = build_scene(rgb=True)
    cam = SimCamera(rgb_scene, view, lambda t: np.zeros((rgb_scene.structure.n_modes, len(t))),
                    SimCameraConfig(fps=500.0, bit_depth=8, rgb=True, read_noise_e=0.0, shot_noise=False))
    cam.arm(n_frames=1, trigger="internal")
    image = next(cam.frames()).image
    assert image.dtype == np.uint8 and image.shape == (80, 96, 3)
    on = cam.truth(0.0).object_id == STRUCTURE
    r, g, b = (image[..., c][on].mean() for c in range(3))
    assert r > g > b  # the orange paint
    noisy = SimCamera(rgb_scene, view, cam.motion, SimCameraConfig(fps=500.0, read_noise_e=20.0), seed=1)
    noisy.arm(n_frames=2, trigger="internal")
    a, b2 = (f.image.astype(float) for f in noisy.frames())
    # Same scene, independent noise: the difference is pure noise of the configured size.
    sigma_dn = np.std(a - b2) / np.sqrt(2)
    assert 0.5 < sigma_dn < 40
    with pytest.raises(InputError, match="bit_depth"):
        SimCameraConfig(bit_depth=10).validate()
    with pytest.raises(InputError, match="exposure_s"):
        SimCameraConfig(fps=1000.0, exposure_s=2e-3).validate()


def test_driver_interface(scene, view):
    """The same calls the capture session makes on every camera: configure, arm, wait, frames, stop."""
    now = [0.05]
    cam = _camera(scene, view, clock=lambda: now[0])
    assert isinstance(cam, CameraDriver)
    cam.configure(TriggerSettings(n_frames=6, mode="external", pretrigger="center", fps=2000.0))
    cam.arm()
    with pytest.raises(CameraTimeout, match="no trigger"):
        cam.wait(0.01)
    cam.trigger_at(0.0812)
    status = cam.wait(1.0)
    assert (status.n_frames, status.first_counter, status.pretrigger_available) == (6, -3, 3)
    assert cam.recording.exposure_start_s[3] == pytest.approx(0.0815)  # the first 2 kHz tick after the edge
    frames = list(cam.frames())
    assert [f.counter for f in frames] == [-3, -2, -1, 0, 1, 2] and frames[0].time_s == pytest.approx(-1.5e-3)
    info = cam.describe()
    assert (info.fps, info.width_px, info.height_px, info.bit_depth) == (2000.0, 96, 80, 12)
    assert info.intrinsics.fx_px == pytest.approx(view.K[0, 0])
    cam.stop()
    with pytest.raises(OdsplatError, match="before arm"):
        cam.wait(0.01)
