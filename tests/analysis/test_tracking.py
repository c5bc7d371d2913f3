"""Point tracking against exact renders of the simulated rig vibrating in its first mode, and a smoke test on a real
Photron recording of a beam."""
from __future__ import annotations

import logging

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from odsplat.analysis.tracking import DEFAULT_METHOD, METHODS, Tracks, good_points, project_displacement, track_points
from odsplat.hil_sim.render import PinholeCamera, expose, render
from odsplat.hil_sim.scene import build_scene
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import look_at
from odsplat.spine.io.video import open_video

AMPLITUDES_PX = (0.02, 0.2, 2.0)  # peak image displacement of the fastest tracked point
N_FRAMES = 24
FPS = 200.0  # 2.4 periods of the 23.5 Hz mode in 24 frames
WINDOW_PX = 15
# The phase method sees window + Gabor support (15 + 2 * 8 px): points keep that far from the edges of the faces,
# where the column occludes the arm or the background (those windows do not move rigidly).
FACE_MARGIN_PX = 16
# Measured rms errors, noise-free (px at 0.02 / 0.2 / 2 px): gradient 0.0002 / 0.0017 / 0.006, lk 0.002 / 0.0056 /
# 0.009, phase 0.0003 / 0.0024 / 0.008. With the sensor's noise all are 0.012-0.019 px.
CLEAN_BOUND = (0.005, 0.02)   # rms error <= a + b * rms(truth)
NOISY_BOUND = (0.025, 0.03)


@pytest.fixture(scope="module")
def view():
    """A 160x120 camera 1 m in front of the column top and arm root (about 1 mm per px), the speckled points on the
    front faces and their world positions from the rendered depth."""
    scene = build_scene()
    cam = PinholeCamera.look_at((0.08, -1.0, 0.54), (0.08, 0.0, 0.54), fx_px=1000.0, width_px=160, height_px=120)
    ref = render(scene.mesh(np.zeros(scene.structure.n_modes)), cam, scene.atlas, background=0.5)
    H, W = ref.depth_m.shape
    v, u = np.mgrid[:H, :W]
    depth = np.where(np.isfinite(ref.depth_m), ref.depth_m, 0.0)[..., None]
    world = (np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(cam.K).T * depth - cam.t) @ cam.R
    g = scene.structure.geometry
    front = (np.abs(world[..., 1] + g.arm_half_width_m) < 1e-4) | (np.abs(world[..., 1] + g.column_half_m) < 1e-4)
    points = good_points(ref.image, binary_erosion(front, iterations=FACE_MARGIN_PX), max_points=30,
                         min_distance_px=10, window_px=WINDOW_PX)
    assert len(points) >= 10
    ij = np.rint(points).astype(int)
    points_m = world[ij[:, 1], ij[:, 0]]
    assert np.abs(cam.project(points_m).px - points).max() < 1e-6
    shapes = scene.structure.mode_shapes(points_m)  # (P, n_modes, 3)
    unit_px = project_displacement(shapes[None, :, 0], points_m, cam.K, cam.R, cam.t)[0]
    m = scene.structure.modes[0]
    t = np.arange(N_FRAMES) / FPS
    wave = np.exp(-m.damping * m.omega * t) * np.sin(m.omega * np.sqrt(1 - m.damping**2) * t)  # 0 at frame 0
    return dict(scene=scene, cam=cam, ref=ref, points=points, points_m=points_m, shapes=shapes,
                q_per_px=wave / np.abs(unit_px).max())


@pytest.fixture(scope="module")
def takes(view):
    """Per amplitude: noise-free radiance frames, the same through the sensor model (12 bit, shot + read noise), and
    the true displacement of the points (exact projection)."""
    scene, cam, points = view["scene"], view["cam"], view["points"]
    rng = np.random.default_rng(7)
    out = {}
    for amplitude in AMPLITUDES_PX:
        q = amplitude * view["q_per_px"]
        clean = np.stack([render(scene.mesh(np.r_[qk, np.zeros(scene.structure.n_modes - 1)]), cam, scene.atlas,
                                 background=0.5).image for qk in q])
        noisy = np.stack([expose(frame, rng=rng) for frame in clean])
        truth = np.stack([cam.project(view["points_m"] + qk * view["shapes"][:, 0]).px - points for qk in q])
        out[amplitude] = dict(clean=clean, noisy=noisy, truth=truth)
    return out


@pytest.fixture(scope="module")
def tracked(view, takes):
    """Tracks by (method, amplitude, noisy), computed once."""
    cache: dict = {}

    def get(method: str, amplitude: float, noisy: bool) -> Tracks:
        key = (method, amplitude, noisy)
        if key not in cache:
            cache[key] = track_points(takes[amplitude]["noisy" if noisy else "clean"], view["points"], method=method,
                                      window_px=WINDOW_PX)
        return cache[key]
    return get


def _rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


# ------------------------------------------------------------------------------------------- projection

def test_project_displacement_is_the_derivative_of_the_projection():
    rng = np.random.default_rng(3)
    R, t = look_at((0.7, -0.9, 0.8), (0.05, 0.02, 0.4))
    K = np.array([[1210.0, 3.5, 330.0], [0.0, 1190.0, 250.0], [0.0, 0.0, 1.0]])  # skewed, non-square pixels
    cam = PinholeCamera(K=K, R=R, t=t, width_px=640, height_px=480)
    points = rng.uniform(-0.2, 0.2, (7, 3)) + (0.05, 0.02, 0.4)
    disp = rng.standard_normal((4, 7, 3))
    got = project_displacement(disp * 1e-3, points, K, R, t)
    eps = 1e-7
    numeric = np.stack([(cam.project(points + eps * d).px - cam.project(points - eps * d).px) / (2 * eps) * 1e-3
                        for d in disp])
    assert got.shape == (4, 7, 2)
    assert np.abs(got - numeric).max() < 1e-6 * np.abs(numeric).max()
    with pytest.raises(InputError, match="behind the camera"):
        project_displacement(disp, np.vstack([points[:6], cam.center_m - 0.1 * R[2]]), K, R, t)
    with pytest.raises(InputError, match="displacement_m"):
        project_displacement(disp[:, :3], points, K, R, t)


def test_first_order_truth_is_exact_enough(view):
    # At the largest modal coordinate of the tests, every mode's exact image motion differs from the first-order
    # one by < 1e-3 px (mode 0 has no depth motion in this view; mode 1 twists towards the camera: 5e-4 px).
    cam, points, points_m = view["cam"], view["points"], view["points_m"]
    q = AMPLITUDES_PX[-1] * view["q_per_px"]
    for k in range(view["scene"].structure.n_modes):
        disp = q[:, None, None] * view["shapes"][None, :, k]
        exact = np.stack([cam.project(points_m + d).px - points for d in disp])
        assert np.abs(exact - project_displacement(disp, points_m, cam.K, cam.R, cam.t)).max() < 1e-3, k


# ------------------------------------------------------------------------------------------- accuracy

@pytest.mark.parametrize("amplitude", AMPLITUDES_PX)
@pytest.mark.parametrize("method", METHODS)
def test_noise_free_tracks_match_the_truth(tracked, takes, method, amplitude):
    truth = takes[amplitude]["truth"]
    tracks = tracked(method, amplitude, False)
    assert tracks.displacement_px.shape == truth.shape and tracks.method == method
    assert np.all(tracks.displacement_px[0] == 0) and np.all(np.isfinite(tracks.displacement_px))
    error = _rms(tracks.displacement_px - truth)
    assert error <= CLEAN_BOUND[0] + CLEAN_BOUND[1] * _rms(truth), (method, amplitude, error)


@pytest.mark.parametrize("amplitude", AMPLITUDES_PX)
@pytest.mark.parametrize("method", METHODS)
def test_tracks_through_sensor_noise_match_the_truth(tracked, takes, method, amplitude):
    truth = takes[amplitude]["truth"]
    error = _rms(tracked(method, amplitude, True).displacement_px - truth)
    assert error <= NOISY_BOUND[0] + NOISY_BOUND[1] * _rms(truth), (method, amplitude, error)


@pytest.mark.parametrize("method", METHODS)
def test_larger_motions_correlate_with_the_truth(tracked, takes, method):
    for amplitude in AMPLITUDES_PX[1:]:
        truth = takes[amplitude]["truth"]
        for noisy in (False, True):
            d = tracked(method, amplitude, noisy).displacement_px
            corr = [np.corrcoef(d[:, i, 0], truth[:, i, 0])[0, 1] for i in range(truth.shape[1])]
            assert min(corr) > 0.99, (amplitude, noisy, min(corr))


def test_default_method_is_the_most_accurate_at_small_motion(tracked, takes):
    for amplitude in AMPLITUDES_PX[:2]:
        truth = takes[amplitude]["truth"]
        errors = {m: _rms(tracked(m, amplitude, False).displacement_px - truth) for m in METHODS}
        assert errors[DEFAULT_METHOD] == min(errors.values()), errors


# ------------------------------------------------------------------------------------------- behaviour

def test_untextured_and_border_points_get_nan_and_a_warning(view, takes, caplog):
    frames = takes[0.2]["clean"]
    flat = binary_erosion(view["ref"].object_id == 0, iterations=WINDOW_PX)  # background 0.5: no texture at all
    background = np.argwhere(flat)[0][::-1]
    points = np.vstack([view["points"][:2], background, [2.0, 60.0]])
    with caplog.at_level(logging.WARNING, logger="odsplat.analysis.tracking"):
        tracks = track_points(frames, points)
    assert "points [2] have too little texture" in caplog.text and "points [3] lie within 9 px" in caplog.text
    assert np.all(np.isnan(tracks.displacement_px[:, 2:])) and np.all(np.isfinite(tracks.displacement_px[:, :2]))
    assert tracks.quality[2] == 0 and tracks.quality[:2].min() > 0.02


@pytest.mark.parametrize("method", METHODS)
def test_streamed_frames_give_the_same_tracks(view, takes, tmp_path, method):
    frames = takes[0.2]["noisy"]
    points = view["points"][:4]
    whole = track_points(frames, points, method=method).displacement_px
    streamed = track_points((f for f in frames), points, method=method, progress=True).displacement_px
    np.save(tmp_path / "take.npy", frames)
    video = track_points(open_video(tmp_path / "take.npy"), points, method=method).displacement_px
    np.testing.assert_array_equal(streamed, whole)
    np.testing.assert_array_equal(video, whole)


def test_good_points_keep_to_the_mask_and_apart(view):
    image = view["ref"].image
    mask = np.zeros(image.shape, bool)
    mask[20:100, 10:70] = True
    points = good_points(image, mask, max_points=12, min_distance_px=9)
    assert 5 <= len(points) <= 12
    assert np.all(mask[points[:, 1].astype(int), points[:, 0].astype(int)])
    gaps = np.linalg.norm(points[:, None] - points[None], axis=2) + np.eye(len(points)) * 1e9
    assert gaps.min() >= 9
    assert len(good_points(np.full((50, 50), 0.3))) == 0


@pytest.mark.parametrize("frames,points,kwargs,match", [
    (np.zeros((3, 40, 40)), [[20, 20]], dict(method="sift"), "method"),
    (np.zeros((3, 40, 40)), [[20, 20]], dict(window_px=14), "window_px"),
    (np.zeros((3, 40, 40)), [[45, 20]], {}, "outside"),
    (np.zeros((3, 40, 40)), [20, 20], {}, "points_px"),
    ([np.zeros((40, 40)), np.zeros((40, 41))], [[20, 20]], {}, "frame 1"),
    (np.zeros((3, 40, 40, 3)), [[20, 20]], {}, "frames"),
    ([], [[20, 20]], {}, "at least one frame"),
])
def test_bad_input_is_named(frames, points, kwargs, match):
    with pytest.raises(InputError, match=match):
        track_points(frames, points, **kwargs)


# ------------------------------------------------------------------------------------------- real data

def test_real_beam_recording(shared_data):
    """pyidi's showcase: a beam filmed at 15 kHz (every 100th frame kept), 640x40 px, vibrating vertically. Its
    long edges are horizontal, so only the two end corners fix x; the rest track y alone (aperture)."""
    path = shared_data / "pyidi-samples" / "data_showcase.cih"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    video = open_video(path)
    points = good_points(video.read(0, 1)[0], max_points=6, min_distance_px=20, window_px=11, quality_level=0.01)
    assert len(points) >= 4
    corners = np.argsort(points[:, 0])[[0, -1]]
    d = {m: track_points(video, points, method=m, window_px=11).displacement_px for m in METHODS}
    for m, disp in d.items():
        assert disp.shape == (75, len(points), 2) and np.all(np.isfinite(disp)), m
        # Measured: 0.6-0.75 px peak to peak vertically; at the corners, horizontal rms a quarter of the vertical.
        ptp_y = np.ptp(disp[..., 1], axis=0)
        assert np.all((ptp_y > 0.4) & (ptp_y < 1.2)), (m, ptp_y)
        assert np.all(disp[:, corners, 0].std(axis=0) < 0.5 * disp[:, corners, 1].std(axis=0)), m
    for m in ("lk", "phase"):  # measured: 0.005-0.014 px rms apart in y, 0.006-0.011 px at the corners in x and y
        assert _rms(d[m][..., 1] - d[DEFAULT_METHOD][..., 1]) < 0.03, m
        assert _rms(d[m][:, corners] - d[DEFAULT_METHOD][:, corners]) < 0.03, m
        for i in range(len(points)):
            assert np.corrcoef(d[m][:, i, 1], d[DEFAULT_METHOD][:, i, 1])[0, 1] > 0.98, (m, i)
