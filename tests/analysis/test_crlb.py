"""The Cramér-Rao bound of displacement (analysis/crlb.py) against hil_sim. The camera's noise model must match the
simulated sensor's. An efficient estimator on rendered, shifted texture must come within reach of the bound.
Smooth texture must get no bound, and so must the direction that every view sees along."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import map_coordinates, spline_filter

from odsplat.analysis.crlb import (
    MIN_PRE_FRAMES,
    NoiseModel,
    _gradients,
    bound_from_information,
    displacement_bound,
    fisher_2d,
    fit_noise_model,
    mode_bound,
    projection_jacobian,
    resolved_2d,
    rest_view,
    sigma_2d_px,
)
from odsplat.analysis.noise import noise_floor
from odsplat.analysis.ods import fit_decay
from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.hil_sim.camera import SimCameraConfig
from odsplat.hil_sim.render import PinholeCamera, TexturedMesh, expose, render
from odsplat.hil_sim.rig import TakeTruth, truth_path
from odsplat.hil_sim.scene import speckle
from odsplat.hil_sim.structure import ModalStructure
from odsplat.reconstruction import PoseResult
from odsplat.reconstruction.pose_result import ViewPose
from odsplat.spine.store import Capture

FPS = 2000.0


def _record(out: Path, *, n_views: int = 1, pretrigger: int = 30, bit_depth: int = 12, full_well_e: float = 20_000.0,
            read_noise_e: float = 30.0, size: tuple[int, int] = (200, 150), seed: int = 1) -> Capture:
    """A simulated capture whose takes hold `pretrigger` frames at rest before the hit."""
    camera = SimCameraConfig(fps=FPS, bit_depth=bit_depth, full_well_e=full_well_e, read_noise_e=read_noise_e)
    report = simulate_capture(out, n_views=n_views, n_frames=pretrigger + 6, pretrigger_frames=pretrigger,
                              record_s=0.1, settings=SimBenchSettings(camera=camera, seed=seed, width_px=size[0],
                                                                      height_px=size[1]))
    assert report.complete
    return Capture.open(out)


def _truth(cap: Capture, name: str) -> TakeTruth:
    return TakeTruth.load(truth_path(cap.takes_dir / f"{name}.h5"))


def _write_true_poses(cap: Capture) -> None:
    """derived/poses.json with every take's true camera (its truth file)."""
    views = []
    for name in cap.take_names():
        tr = _truth(cap, name)
        with cap.open_take(name) as r:
            h, w = r.frame_shape[:2]
            view = int(r.view)
        views.append(ViewPose(name, "take", view, "tags", tr.camera_K, tr.camera_R, tr.camera_t, w, h, None, None,
                              None))
    PoseResult(views, np.zeros((0, 3)), np.zeros((0, 1)), np.zeros(0), "tags", None, None, None, None, len(views),
               len(views), []).write(cap)


# ---------------------------------------------------------------------------------------------- the camera

@pytest.mark.parametrize("bit_depth, full_well_e, read_noise_e", [(12, 20_000.0, 30.0), (8, 2_000.0, 20.0)])
def test_the_noise_model_recovers_the_simulated_camera(tmp_path, bit_depth, full_well_e, read_noise_e):
    """The photon-transfer line fitted on a take's 29 frames at rest (of 30 before the trigger) gives the simulated
    sensor's gain (top code / full well, DN per electron) and read noise within 15 %. That holds for 12-bit codes
    in 16-bit words and for 8-bit ones. The read noise is set where the scene's darkest pixels can show it: hil_sim's
    scene is no darker than 170 DN of 4095, where a 5 e- read noise (1 DN) is 3 % of the shot noise's variance."""
    cap = _record(tmp_path / "cap", bit_depth=bit_depth, full_well_e=full_well_e, read_noise_e=read_noise_e)
    model = rest_view(cap, cap.take_names()[0]).noise
    gain = (2 ** bit_depth - 1) / full_well_e
    assert model.measured and model.n_frames == 29 and model.step_dn == 1.0
    assert model.gain_dn == pytest.approx(gain, rel=0.15)
    assert model.read_dn == pytest.approx(read_noise_e * gain, rel=0.15)
    assert model.read_e == pytest.approx(read_noise_e, rel=0.15)


def test_too_few_frames_at_rest_leave_the_quantisation_alone(tmp_path, caplog):
    """With 2 frames before the trigger (one of them too close to it) there is nothing to measure the noise on: the
    model is the quantisation's, 1/12 DN^2 at every brightness, and the log says so."""
    cap = _record(tmp_path / "cap", pretrigger=2)
    with caplog.at_level("WARNING", logger="odsplat.analysis.crlb"):
        model = rest_view(cap, cap.take_names()[0]).noise
    assert not model.measured and model.n_frames < MIN_PRE_FRAMES
    assert model.variance(np.array([0.0, 2000.0])) == pytest.approx([1 / 12, 1 / 12])
    assert "quantisation only" in caplog.text


def test_a_shifted_code_step_is_found():
    """12-bit codes shifted into the top of 16-bit words step by 16: the quantisation is 16^2 / 12 DN^2."""
    rng = np.random.default_rng(0)
    frames = (expose(np.full((40, 40), 0.4), rng=rng, bit_depth=12) for _ in range(8))
    model = fit_noise_model(np.stack([f.astype(np.uint16) << 4 for f in frames]), 12)
    assert model.step_dn == 16.0


# ---------------------------------------------------------------------------------------------- 2D

W = H = 128
FX_PX = 400.0
Z_M = 1.0


def _plane(dx_px: float = 0.0, dy_px: float = 0.0, texture: np.ndarray | None = None) -> np.ndarray:
    """hil_sim's render of a fronto-parallel textured square 1 m in front of the camera, moved by (dx, dy) px."""
    cam = PinholeCamera(K=np.array([[FX_PX, 0, (W - 1) / 2], [0, FX_PX, (H - 1) / 2], [0, 0, 1.0]]), R=np.eye(3),
                        t=np.zeros(3), width_px=W, height_px=H)
    tex = np.full((512, 512), 0.5, np.float32) if texture is None else texture
    half = 0.25
    v = np.array([[-half, -half, Z_M], [half, -half, Z_M], [half, half, Z_M], [-half, half, Z_M]])
    v[:, 0] += dx_px * Z_M / FX_PX
    v[:, 1] += dy_px * Z_M / FX_PX
    uv = np.array([[-0.5, -0.5], [511.5, -0.5], [511.5, 511.5], [-0.5, 511.5]], np.float32)
    mesh = TexturedMesh(v, np.array([[0, 1, 2], [0, 2, 3]], np.int32), uv, np.ones(2, np.int16))
    return render(mesh, cam, tex, supersample=4).image


def _gauss_newton(rest: np.ndarray, frame: np.ndarray, centres: np.ndarray, var: np.ndarray, window_px: int
                  ) -> np.ndarray:
    """(P, 2) displacement d of each window with frame(p) = rest(p - d): Gauss-Newton on the rest image's cubic
    spline, each pixel weighted by 1 / var (the efficient estimator for Gaussian noise)."""
    r = np.arange(window_px) - window_px // 2
    ys = centres[:, 1, None, None] + r[None, :, None] + 0 * r[None, None, :]
    xs = centres[:, 0, None, None] + r[None, None, :] + 0 * r[None, :, None]
    iy, ix = ys.astype(int), xs.astype(int)
    img, w = frame[iy, ix].astype(float), 1.0 / var[iy, ix]
    coef = [spline_filter(a) for a in (rest, *_gradients(rest))]
    d = np.zeros((len(centres), 2))
    for _ in range(5):
        at = [ys - d[:, 1, None, None], xs - d[:, 0, None, None]]
        ref, gx, gy = (map_coordinates(c, at, order=3, prefilter=False) for c in coef)
        res = (img - ref) * w
        normal = np.stack([np.stack([np.sum(gx * gx * w, (1, 2)), np.sum(gx * gy * w, (1, 2))], -1),
                           np.stack([np.sum(gx * gy * w, (1, 2)), np.sum(gy * gy * w, (1, 2))], -1)], -2)
        rhs = -np.stack([np.sum(gx * res, (1, 2)), np.sum(gy * res, (1, 2))], -1)
        d = d + np.linalg.solve(normal, rhs[..., None])[..., 0]
    return d


def test_an_efficient_estimator_reaches_the_bound():
    """hil_sim's speckle (3 px grains), rendered at rest and moved by (0.3, -0.2) px, exposed with the simulated
    sensor's noise. The rest image is the mean of 16 exposures, as before an impact, and 32 independent moved
    exposures follow. Gauss-Newton over 7x7 windows (196 of them) is the estimator. Its scatter over the draws, in
    units of each window's bound, is 1.00 (measured). Its floor is 1, with the rest image's own noise adding
    3 %: it must lie in [0.9, 2]. Its mean is the true shift within a bound."""
    rng = np.random.default_rng(0)
    texture = speckle((512, 512), 8.0, rng)
    shift = np.array([0.3, -0.2])
    sensor = dict(bit_depth=12, full_well_e=20_000.0, read_noise_e=5.0)
    rest_radiance, moved_radiance = _plane(texture=texture), _plane(*shift, texture=texture)
    rest_frames = np.stack([expose(rest_radiance, rng=rng, **sensor) for _ in range(16)])
    model = fit_noise_model(rest_frames, 12)
    rest = rest_frames.astype(float).mean(axis=0)
    g = np.arange(12, W - 12, 8)
    centres = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2).astype(float)
    sigma = sigma_2d_px(fisher_2d(rest, model, centres, 7))                                   # (P, 2)
    assert np.all(np.isfinite(sigma)) and 0.002 < np.median(sigma) < 0.05
    err = np.stack([_gauss_newton(rest, expose(moved_radiance, rng=rng, **sensor), centres, model.variance(rest), 7)
                    - shift for _ in range(32)])                                              # (D, P, 2)
    z = err / sigma[None]
    scatter = np.sqrt(np.mean((z - z.mean(axis=0)) ** 2, axis=(0, 1)) * 32 / 31)
    assert np.all(scatter >= 0.9) and np.all(scatter <= 2.0), scatter
    assert np.all(np.abs(np.mean(z, axis=(0, 1))) < 1.0)


def test_a_smooth_patch_has_no_bound_and_its_textured_half_has_one():
    """A plane whose left half is plain paint and right half speckle: the windows on the paint get no 2D direction
    (infinite sigma), and no 3D bound either, never a number from noise. Those on the speckle get a finite one."""
    rng = np.random.default_rng(1)
    texture = speckle((512, 512), 8.0, rng)
    texture[:, :256] = 0.5
    frames = np.stack([expose(_plane(texture=texture), rng=rng) for _ in range(16)])
    model = fit_noise_model(frames, 12)
    centres = np.array([[20.0, 64.0], [40.0, 40.0], [90.0, 64.0], [110.0, 90.0]])
    J = resolved_2d(fisher_2d(frames.astype(float).mean(axis=0), model, centres, 7))
    sigma = sigma_2d_px(J)
    assert np.all(np.isinf(sigma[:2])) and np.all(np.isfinite(sigma[2:]))
    points = np.column_stack([(centres - (W - 1) / 2) * Z_M / FX_PX, np.full(len(centres), Z_M)])
    P = projection_jacobian(points, np.array([[FX_PX, 0, (W - 1) / 2], [0, FX_PX, (H - 1) / 2], [0, 0, 1]]),
                            np.eye(3), np.zeros(3))
    b = bound_from_information(np.einsum("nia,nij,njb->nab", P, J, P))
    assert not b.resolved.any() and np.all(np.isinf(b.rms_m)) and np.all(np.isinf(b.worst_sigma_m[:2]))


# ---------------------------------------------------------------------------------------------- 3D

def _look_at(eye) -> tuple[np.ndarray, np.ndarray]:
    """R, t of a camera at eye looking at the origin."""
    cam = PinholeCamera.look_at(np.asarray(eye, float), np.zeros(3), up=(0.0, 1.0, 0.0) if abs(eye[1]) < 1 else
                                (1.0, 0.0, 0.0), fx_px=FX_PX, width_px=W, height_px=H)
    return cam.R, cam.t


def test_the_direction_every_view_looks_along_is_unresolved():
    """A point at the origin seen from +z and -z, each view with 1e4 /px^2 of information in every image direction
    (sigma 0.01 px): the worst direction is z (within 5 degrees), its sigma and z's are infinite, and x and y
    keep the analytic sigma 0.01 px x 1 m / 400 px / sqrt(2). A third view along x resolves z with the analytic
    sigma (one view's worth)."""
    K = np.array([[FX_PX, 0, (W - 1) / 2], [0, FX_PX, (H - 1) / 2], [0, 0, 1]])
    J = np.eye(2) * 1e4
    point = np.zeros((1, 3))

    def info(eyes):
        return sum(np.einsum("nia,ij,njb->nab", P, J, P)
                   for P in (projection_jacobian(point, K, *_look_at(e)) for e in eyes))

    one = 0.01 * 1.0 / FX_PX
    b = bound_from_information(info([(0, 0, 1.0), (0, 0, -1.0)]))
    angle = np.degrees(np.arccos(min(abs(float(b.worst_dir[0, 2])), 1.0)))
    assert angle < 5.0 and not b.resolved[0] and np.isinf(b.worst_sigma_m[0]) and np.isinf(b.rms_m[0])
    assert np.isinf(b.sigma_axis_m[0, 2])
    assert b.sigma_axis_m[0, :2] == pytest.approx([one / np.sqrt(2)] * 2, rel=1e-6)
    b3 = bound_from_information(info([(0, 0, 1.0), (0, 0, -1.0), (1.0, 0, 0)]))
    assert b3.resolved[0]
    assert b3.sigma_axis_m[0] == pytest.approx([one / np.sqrt(2), one / np.sqrt(3), one], rel=1e-6)


@pytest.fixture(scope="module")
def two_views(tmp_path_factory) -> Capture:
    """Two views on the simulated rig (400x300, 24 frames at rest, 30 e- read noise), each take's true camera as its
    pose; not synced (the trigger frame marks the impact)."""
    cap = _record(tmp_path_factory.mktemp("crlb") / "cap", n_views=2, pretrigger=24, size=(400, 300), seed=2)
    _write_true_poses(cap)
    return cap


def test_displacement_bound_on_a_simulated_capture(two_views):
    """The rig's 256 surface points against a measured floor of 20 um. Points that one view alone sees are
    unresolved along that camera's ray (within 5 degrees). Those both see are resolved, with a bound between 1 and
    100 um (1 px is about 4 mm there) and the quantisation's bound far below it. The ratio is 20 um over the
    bound, and the summary is plain JSON."""
    cap = two_views
    tr = _truth(cap, cap.take_names()[0])
    pts = tr.surface_points_m
    measured = np.full(len(pts), 20e-6)
    b = displacement_bound(cap, pts, measured)
    assert b is not None and len(b.views) == 2
    gain = 4095 / 20_000.0
    for v in b.views:
        assert v.noise.gain_dn == pytest.approx(gain, rel=0.15)
        assert v.noise.read_dn == pytest.approx(30 * gain, rel=0.15)
    two, one = b.n_views == 2, b.n_views == 1
    assert two.sum() > 100 and one.sum() > 10
    assert b.frame.resolved[two].all() and not b.frame.resolved[one].any()
    assert np.all((b.bound_m[two] > 1e-6) & (b.bound_m[two] < 100e-6))
    assert np.all(b.quantisation_m[two] < 0.1 * b.bound_m[two])
    angles = []
    for name in cap.take_names():
        t = _truth(cap, name)
        ray = pts[one] - (-t.camera_R.T @ t.camera_t)
        ray /= np.linalg.norm(ray, axis=1, keepdims=True)
        angles.append(np.degrees(np.arccos(np.clip(np.abs(np.sum(ray * b.frame.worst_dir[one], axis=1)), 0, 1))))
    assert np.max(np.min(angles, axis=0)) < 5.0          # along the ray of the view that sees the point
    assert np.min(np.max(angles, axis=0)) > 20.0         # and not the other one's
    assert b.ratio[two] == pytest.approx(20e-6 / b.bound_m[two])
    assert np.isnan(b.ratio[one]).all()
    assert b.median_ratio == pytest.approx(float(np.median(20e-6 / b.bound_m[b.frame.resolved])))
    json.dumps(b.summary(), allow_nan=False)


def test_each_mode_floor_against_the_bound(two_views):
    """A NoiseFloor made from white noise of 20 um on the sensors and the points, read through the decay fit of the
    rig's poles. With the sensors' bound at 20 um too, each mode's floor from the bound equals the measured one, up
    to the measured noise's colour at the mode: ratio 0.96-1.00 measured, 1 within 10 %. With the bound from the
    capture, the ratio is the sensors' noise over that bound, times the colour."""
    rng = np.random.default_rng(3)
    s = ModalStructure()
    wn = 2 * np.pi * np.asarray(s.freqs_hz)
    poles = -np.asarray(s.dampings) * wn + 1j * wn * np.sqrt(1 - np.asarray(s.dampings) ** 2)
    t = np.arange(-4, 240) / FPS
    sigma = 20e-6
    sensors, points = rng.normal(0, sigma, (len(t), 4)), rng.normal(0, sigma, (len(t), 3 * 50))
    nf = noise_floor(t, sensors, points, fit_decay(t, np.concatenate([sensors, points], axis=1), poles, t_min_s=1.5e-3))
    flat = mode_bound(nf, np.full(4, sigma))
    assert flat.ratio == pytest.approx(np.ones(len(poles)), rel=0.1)
    cap = two_views
    tr = _truth(cap, cap.take_names()[0])
    dirs = np.nan_to_num(tr.sensor_directions, nan=0.0)
    dirs[np.linalg.norm(dirs, axis=1) == 0] = (0.0, 0.0, 1.0)
    b = displacement_bound(cap, tr.surface_points_m, np.full(len(tr.surface_points_m), sigma), noise=nf,
                           sensors_m=tr.sensor_points_m, sensor_dirs=dirs)
    m = b.modes
    assert m is not None and np.all(np.isfinite(m.sensor_bound_m)) and np.all(m.sensor_bound_m > 0)
    rms = np.sqrt(np.mean(nf.sensor_sigma_m ** 2)) * np.sqrt(nf.spectrum_gain) / np.sqrt(np.mean(m.sensor_bound_m ** 2))
    assert m.ratio == pytest.approx(rms, rel=1e-9)


def test_the_variance_never_falls_below_the_quantisation():
    model = NoiseModel(gain_dn=0.2, read_dn=0.0, step_dn=1.0, n_frames=10, n_pixels=100)
    assert model.variance(np.array([-5.0, 0.0, 100.0])) == pytest.approx([1 / 12, 1 / 12, 20 + 1 / 12])


def test_the_floor_per_direction_follows_the_bound_and_flags_what_the_views_do_not_resolve():
    """Points whose views resolve x and y ten times better than z: a mode moving 10 um along x stands above the
    floor there, 5 um along z does not (the z floor is 10x the x floor); a mode moving 40 um along z stands above.
    The shares, the per-point flags and the report's line follow; the shapes the analysis keeps drop what is below."""
    from odsplat.analysis.crlb import DisplacementBound, bound_from_information, direction_floor

    n = 20
    sigma = np.array([1.0, 1.0, 10.0]) * 1e-6                                    # per frame, per axis
    frame = bound_from_information(np.repeat(np.diag(1 / sigma ** 2)[None], n, axis=0))
    measured = np.full(n, 1e-6)
    bound = DisplacementBound(np.zeros((n, 3)), frame, frame.rms_m, measured, measured / frame.rms_m,
                              np.ones(n, bool), np.full(n, 4), (), frame.rms_m, frame.rms_m)
    amps = np.zeros((2, n, 3), complex)
    amps[0, :, 0], amps[0, :, 2] = 5e-6, 2.5e-6                                   # 2|C| = 10 um along x, 5 um along z
    amps[1, :, 2] = 20e-6                                                         # 40 um along z
    d = direction_floor(bound, amps, np.ones(2))
    # floor per axis: 4.36 x 1 um x sigma_axis / rms = 0.75, 0.75 and 7.5 um
    assert d.below[0, :, 0].sum() == 0 and d.below[0, :, 2].all() and not d.below[1, :, 2].any()
    assert d.unresolved_axis_share[0, 2] == pytest.approx(1.0) and d.unresolved_axis_share[0, 0] == pytest.approx(0)
    assert d.unresolved_share[0] == pytest.approx(25 / 125) and d.unresolved_share[1] == pytest.approx(0)
    assert d.point_resolved[0].all() and d.point_resolved[1].all()
    assert d.noise_axes().tolist() == [[False, False, True], [False, False, False]]   # x, y: no motion, no power
    lines = d.lines(np.array([30.0, 90.0]))
    assert len(lines) == 1 and lines[0].startswith("30.0 Hz: its motion along z (100 %)")
