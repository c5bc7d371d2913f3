"""The physical limit of the video's displacement: the Cramér-Rao bound that the camera's shot, read and quantisation
noise sets on each surface point's motion, given the image texture in each view and the views combined in 3D.
It also compares the measured noise floor (analysis/noise.py) with that bound (docs/analysis.md, "The physical
limit").

The camera's noise is measured on the frames before the impact, where the structure is at rest. Each pixel's
temporal variance against its mean fits the photon-transfer line var(I) = read^2 + gain I + step^2/12 (digital
numbers, DN). A point's 2D image displacement d, read from a window W of pixels around it, has the Fisher information

    J = sum_W grad I grad I^T / var(I)                     (2 x 2, 1/px^2; grad I of the rest image)

and its 3D displacement u has F = sum over the views that see it of P^T J P, with P (2 x 3, px/m) the projection's
Jacobian there. No unbiased estimator of u from one frame per view does better than cov(u) = F^-1. The window
is the point's own cell by default: its spacing to its neighbours, seen in the view. Those cells tile the image,
so two points never count the same pixel. A direction that F leaves singular is reported as infinite, never
as a number read from a near-singular inverse."""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.ndimage import spline_filter1d
from scipy.spatial import cKDTree

from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import TakeSync, load_sync

from .crosscheck import _poses, _to_pixels, _visible
from .noise import FLOOR_SIGMAS, NoiseFloor
from .ods import SurfaceMotion

log = logging.getLogger(__name__)

MIN_PRE_FRAMES = 3         # frames at rest needed to measure the noise; fewer: quantisation only
IMPACT_MARGIN_FRAMES = 1   # without a sync result: frames this close before the trigger frame are left out (the
#                            force rises through the trigger level a fraction of a frame after the impact's onset)
MIN_BIN_PIXELS = 50        # pixels per brightness bin of the photon-transfer fit
N_BINS = 32
MAX_SIGMA_PX = 1.0         # a view's 2D direction counts only where its bound is at most this. Beyond a pixel per
#                            frame, the linearised model that the bound assumes no longer holds: no texture
RCOND = 1e-6               # a 3D direction whose information is below this times the best one's is unresolved
#                            (its sigma would be 1000x the best-resolved direction's)
PERP_TOL = 2e-3            # an axis within this (radians) of perpendicular to every unresolved direction keeps a
#                            finite sigma
MIN_CELL_PX, MAX_CELL_PX = 3, 31   # the window's side: at least the derivative's support, at most a small patch
NOISE_AXIS_SHARE = 0.9     # a mode's shape along a world axis with this share of its power below the floor there is
#                            the noise's (DirectionFloor.noise_axes): the plate's in-plane motion, on hil_sim
SENSOR_DRAWS = 256         # noise draws at the bound through the sensors' reading (SurfaceMotion.at_points)
# The gradient is the derivative of the rest image's cubic B-spline interpolant at the pixels (the model the 2D
# tracker fits, analysis/tracking.py). On hil_sim's speckle (about 3 px grains) it reads the true image derivative
# (from renders shifted by +-0.05 px) within 1.5 %. A central difference reads that texture 12 % low. Farid and
# Simoncelli's matched pair, which the linear motion model uses on prefiltered images, reads it 39 % low, since it
# is the derivative of the prefiltered image. Every such shortfall puts the bound that much high.


def _gradients(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d/dx and d/dy (DN per px): the cubic B-spline interpolant's derivative at the pixels, mirrored borders."""
    out = []
    for axis in (1, 0):
        c = spline_filter1d(np.asarray(image, np.float64), order=3, axis=axis, mode="mirror")
        lo = np.take(c, np.r_[1, np.arange(c.shape[axis] - 1)], axis=axis)        # c[i-1], mirrored at 0
        hi = np.take(c, np.r_[np.arange(1, c.shape[axis]), c.shape[axis] - 2], axis=axis)
        out.append(0.5 * (hi - lo))
    return out[0], out[1]


def _kernel_power() -> float:
    """sum(k^2) of the derivative's 2D kernel k: the rest image's own noise, var / n_rest per pixel, adds var *
    sum(k^2) / n_rest to each squared derivative. The x-y cross term vanishes (k_x odd in x, k_y even in x)."""
    delta = np.zeros((65, 65))
    delta[32, 32] = 1.0
    return float(np.sum(_gradients(delta)[0] ** 2))


_KERNEL_POWER = _kernel_power()


# ---------------------------------------------------------------------------------------------- the camera

@dataclass(frozen=True)
class NoiseModel:
    """A camera's temporal noise in digital numbers: var(I) = read_dn^2 + gain_dn * I + step_dn^2 / 12."""

    gain_dn: float          # DN per electron: the photon-transfer slope (variance per DN of brightness)
    read_dn: float          # read noise, DN rms, quantisation apart
    step_dn: float          # the quantisation step (1 for plain codes; 16 for 12-bit codes shifted into 16 bits)
    n_frames: int           # the frames at rest it was measured on
    n_pixels: int           # pixels that took part in the fit (not clipped)
    measured: bool = True   # False: fewer than MIN_PRE_FRAMES frames at rest, quantisation only

    @property
    def read_e(self) -> float:
        """Read noise in electrons (NaN without a gain)."""
        return self.read_dn / self.gain_dn if self.gain_dn > 0 else float("nan")

    def variance(self, intensity_dn) -> np.ndarray:
        """var(I) in DN^2 at brightness I (DN); never below the quantisation's step^2 / 12."""
        i = np.maximum(np.asarray(intensity_dn, float), 0.0)
        return self.read_dn ** 2 + self.gain_dn * i + self.step_dn ** 2 / 12.0

    def describe(self) -> str:
        if not self.measured:
            return (f"quantisation only (step {self.step_dn:g} DN): {self.n_frames} frame(s) at rest, "
                    f"fewer than {MIN_PRE_FRAMES}")
        return (f"gain {self.gain_dn:.4g} DN/e-, read noise {self.read_dn:.3g} DN ({self.read_e:.3g} e-), step "
                f"{self.step_dn:g} DN, from {self.n_frames} frames at rest over {self.n_pixels} pixels")


def _quant_step(frames: np.ndarray) -> float:
    """The codes' step: the greatest common divisor of the values (a 12-bit camera in 16-bit words may shift its
    codes by 4 bits); 1 for non-integer data."""
    if frames.dtype.kind not in "ui":
        return 1.0
    values = np.unique(frames[: min(len(frames), 4)])
    values = values[values > 0].astype(np.int64)
    return float(max(np.gcd.reduce(values), 1)) if len(values) else 1.0


def _chi2_median_ratio(dof: int) -> float:
    """median(chi2_dof) / dof: a sample variance's median lies below the true variance by this factor."""
    from scipy.stats import chi2

    return float(chi2.median(max(dof, 1)) / max(dof, 1))


def _chi2_tail(dof: int) -> float:
    """chi2_dof's 1 - 1e-4 quantile over dof: a sample variance lies below this times the true one but for 1e-4."""
    from scipy.stats import chi2

    return float(chi2.ppf(1 - 1e-4, max(dof, 1)) / max(dof, 1))


def _moments(raw: np.ndarray, bit_depth: int | None, step: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of frames (T, H, W[, C]) (colour: the channels' mean): the temporal mean, the variance (ddof 1)
    and whether any frame touches zero or the top code. Accumulated frame by frame in float64, so that memory
    holds two images, not the frames in float."""
    top = np.inf
    if raw.dtype.kind in "ui":
        top = float(2 ** int(bit_depth) - 1) if bit_depth and step == 1 else float(np.iinfo(raw.dtype).max)
    total = total2 = None
    clipped = np.zeros(raw.shape[1:3], bool)
    for f in raw:
        hit = (f <= 0) | (f >= top - step + 1) if raw.dtype.kind in "ui" else np.zeros(f.shape, bool)
        clipped |= hit.any(axis=-1) if hit.ndim == 3 else hit
        g = f.astype(np.float64)
        g = g.mean(axis=-1) if g.ndim == 3 else g
        total = g.copy() if total is None else total + g
        total2 = g * g if total2 is None else total2 + g * g
    n = len(raw)
    mean = total / n
    return mean, np.maximum(total2 - n * mean * mean, 0.0) / (n - 1), clipped


def fit_noise_model(frames: np.ndarray, bit_depth: int | None = None) -> NoiseModel:
    """The photon-transfer line from frames (T, H, W) or (T, H, W, C) of a static scene (colour: the channels'
    mean). The fit uses the mean variance over each of N_BINS bins, spaced evenly in brightness. That mean is
    unbiased and lies exactly on the line. A pixel whose variance exceeds what noise gives but once in 1e4 (against
    its bin's level: the median, less the chi-square median's bias) has moved, and is left out. So is a pixel
    that touches zero or the top code, because clipping hides its noise."""
    raw = np.asarray(frames)
    step = _quant_step(raw)
    n = len(raw)
    if n < MIN_PRE_FRAMES:
        model = NoiseModel(0.0, 0.0, step, n, 0, measured=False)
        log.warning("camera noise: %s", model.describe())
        return model
    mean, var, clipped = _moments(raw, bit_depth, step)
    mean, var = mean[~clipped], var[~clipped]
    # bins even in brightness, not in count: the few dark pixels set the line's intercept (the read noise)
    edges = np.unique(np.linspace(mean.min(), mean.max(), N_BINS + 1)) if mean.size else np.zeros(1)
    which = np.clip(np.searchsorted(edges, mean, side="right") - 1, 0, max(len(edges) - 2, 0))
    xs, ys, ws = [], [], []
    bias, cut = _chi2_median_ratio(n - 1), _chi2_tail(n - 1)
    for b in range(max(len(edges) - 1, 0)):
        sel = which == b
        if sel.sum() >= MIN_BIN_PIXELS:
            still = sel & (var <= cut * float(np.median(var[sel])) / bias)     # noise alone passes 1 - 1e-4
            xs.append(float(mean[still].mean()))
            ys.append(float(var[still].mean()))
            ws.append(np.sqrt(still.sum()))
    if len(xs) >= 2 and np.ptp(xs) > 0:
        # each bin's variance is known to a fixed relative error (1 / sqrt(its pixels)), so weight by count / value
        gain, intercept = np.polyfit(xs, ys, 1, w=np.array(ws) / np.maximum(ys, 1e-12))
    else:
        gain, intercept = 0.0, float(np.median(var)) / bias if var.size else step ** 2 / 12.0
    gain = max(float(gain), 0.0)
    read2 = max(float(intercept) - step ** 2 / 12.0, 0.0)
    return NoiseModel(gain, float(np.sqrt(read2)), step, n, int(mean.size))


@dataclass(frozen=True)
class RestView:
    """One posed take at rest: the mean of its frames before the impact (grey, DN) and the camera's noise in them."""

    take: str
    rest_dn: np.ndarray     # (H, W)
    noise: NoiseModel
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray

    @property
    def n_rest(self) -> int:
        return self.noise.n_frames


def pre_impact_frames(counters: np.ndarray, trigger_frame: int | None, sync: TakeSync | None) -> np.ndarray:
    """Indices of a take's frames whose exposure ends before the impact. With the take's sync (its offset_s: the
    middle of counter 0's exposure after the impact onset), the sync's timing decides. Without it, the frames
    before the camera's trigger frame do, less IMPACT_MARGIN_FRAMES. The sync's `_rest` picks the frames at rest
    the same way."""
    idx = np.arange(len(counters))
    if sync is not None and sync.offset_s is not None and sync.period_s:
        half = 0.5 * (sync.exposure_s or sync.period_s)
        ends = sync.offset_s + np.asarray(counters, float) * sync.period_s + half
        return idx[ends < 0]
    if trigger_frame is not None:
        return idx[idx < trigger_frame - IMPACT_MARGIN_FRAMES]
    return idx[np.asarray(counters) < -IMPACT_MARGIN_FRAMES]


def rest_view(capture: Capture, name: str, pose: dict | None = None, sync: TakeSync | None = None) -> RestView:
    """A take's rest image and noise model from its frames before the impact (`pre_impact_frames`), read through
    the capture's take reader; pose: its camera (K, R, t), None for identity placeholders."""
    with capture.open_take(name) as reader:
        if not reader.has_frames:
            raise InputError(reader.path, "this take holds no frames to measure the camera's noise on")
        pre = pre_impact_frames(reader.frame_counter, reader.trigger.camera_trigger_frame, sync)
        bit_depth = reader.bit_depth
        frames = reader.read_frames(0, int(pre[-1]) + 1)[pre] if len(pre) else reader.read_frames(0, 1)
    model = fit_noise_model(frames if len(pre) else frames[:0], bit_depth)
    if not len(pre):                    # the step from the one frame read, though none is at rest
        model = replace(model, step_dn=_quant_step(frames))
    rest = np.zeros(frames.shape[1:3])
    for f in frames:
        rest += f.mean(axis=-1) if f.ndim == 3 else f
    rest /= len(frames)
    p = pose or {"K": np.eye(3), "R": np.eye(3), "t": np.zeros(3)}
    return RestView(name, rest, model, *(np.asarray(p[k], float) for k in ("K", "R", "t")))


# ---------------------------------------------------------------------------------------------- 2D information

@dataclass(frozen=True)
class InformationImage:
    """Per pixel grad I grad I^T / var(I) (1/px^2), debiased for the rest image's own noise, as summed-area tables
    (H+1, W+1, 3) of its xx, xy and yy parts: the information of any window in four look-ups."""

    table: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.table.shape[0] - 1, self.table.shape[1] - 1

    def window(self, centres_px: np.ndarray, half_px) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2, 2) information of the square windows of side 2 half + 1 around the pixels nearest centres (N, 2)
        (x, y), and (N,) bool: the window lies inside the image (outside ones: zero)."""
        c = np.rint(np.asarray(centres_px, float)).astype(int).reshape(-1, 2)
        h = np.broadcast_to(np.asarray(half_px, int), (len(c),))
        H, W = self.shape
        x0, x1, y0, y1 = c[:, 0] - h, c[:, 0] + h + 1, c[:, 1] - h, c[:, 1] + h + 1
        inside = (x0 >= 0) & (y0 >= 0) & (x1 <= W) & (y1 <= H)
        x0, x1 = np.clip(x0, 0, W), np.clip(x1, 0, W)
        y0, y1 = np.clip(y0, 0, H), np.clip(y1, 0, H)
        s = self.table[y1, x1] - self.table[y0, x1] - self.table[y1, x0] + self.table[y0, x0]      # (N, 3)
        J = np.stack([s[:, 0], s[:, 1], s[:, 1], s[:, 2]], axis=1).reshape(-1, 2, 2)
        J[~inside] = 0.0
        return J, inside


def information_image(rest_dn: np.ndarray, noise: NoiseModel, *, quantisation_only: bool = False
                      ) -> InformationImage:
    """The per-pixel Fisher information of a rest image (H, W) in DN. The rest image's own noise, var / n_rest per
    pixel through the derivative, is taken out of the squared gradients. quantisation_only: the information that
    a noiseless sensor with the same quantisation step would give (a baseline)."""
    img = np.asarray(rest_dn, np.float64)
    gx, gy = _gradients(img)
    var = noise.variance(img)
    weight = 1.0 / (np.full_like(var, noise.step_dn ** 2 / 12.0) if quantisation_only else var)
    bias = var * _KERNEL_POWER / max(noise.n_frames, 1) * weight
    parts = np.stack([gx * gx * weight - bias, gx * gy * weight, gy * gy * weight - bias], axis=-1)
    table = np.zeros((img.shape[0] + 1, img.shape[1] + 1, 3))
    table[1:, 1:] = parts.cumsum(axis=0).cumsum(axis=1)
    return InformationImage(table)


def fisher_2d(rest_dn: np.ndarray, noise: NoiseModel, centres_px: np.ndarray, window_px: int) -> np.ndarray:
    """(N, 2, 2) the Fisher information (1/px^2) of the 2D displacement of square windows of side window_px (odd)
    around centres_px (N, 2) (x, y) in one frame against the rest image; zero for windows off the image."""
    if int(window_px) != window_px or window_px < 1 or window_px % 2 == 0:
        raise InputError("fisher_2d.window_px", f"expected an odd number of pixels, got {window_px}")
    return information_image(rest_dn, noise).window(centres_px, int(window_px) // 2)[0]


def resolved_2d(J: np.ndarray, max_sigma_px: float = MAX_SIGMA_PX) -> np.ndarray:
    """(N, 2, 2) J with the directions whose bound exceeds max_sigma_px (no texture along them) set to zero."""
    lam, vec = np.linalg.eigh(0.5 * (J + np.swapaxes(J, 1, 2)))
    lam = np.where(lam >= 1.0 / max_sigma_px ** 2, lam, 0.0)
    return np.einsum("nij,nj,nkj->nik", vec, lam, vec)


def sigma_2d_px(J: np.ndarray) -> np.ndarray:
    """(N, 2) the bound's standard deviation along x and y (px); inf where a direction is unresolved."""
    lam, vec = np.linalg.eigh(J)
    out = np.zeros((len(J), 2))
    for k in range(2):
        w = vec[:, :, k] ** 2                                      # (N, 2) each axis's share of direction k
        ok = lam[:, k] > 0
        out += np.where(ok[:, None], w / np.where(ok, lam[:, k], 1.0)[:, None], np.where(w > PERP_TOL ** 2, np.inf, 0))
    return np.sqrt(out)


# ---------------------------------------------------------------------------------------------- 3D

def projection_jacobian(points_m: np.ndarray, K, R, t) -> np.ndarray:
    """(N, 2, 3) d(pixel) / d(world point), px per metre, of a pinhole (K, R, t)."""
    K, R = np.asarray(K, float), np.asarray(R, float)
    cam, uv = _to_pixels(points_m, K, R, t)
    z = cam[:, 2]
    d = (K[None, :2, :] - uv[:, :, None] * K[None, 2:3, :]) / np.where(z > 0, z, 1.0)[:, None, None]
    return d @ R


@dataclass(frozen=True)
class Bound3D:
    """The 3D bound per point from its Fisher information F (N, 3, 3), 1/m^2."""

    sigma_axis_m: np.ndarray    # (N, 3) sqrt(diag F^-1) per world axis; inf along a direction no view resolves
    worst_dir: np.ndarray       # (N, 3) unit: the direction of F's smallest eigenvalue (the worst-resolved)
    worst_sigma_m: np.ndarray   # (N,) the bound along it; inf where unresolved
    resolved: np.ndarray        # (N,) bool: F is well conditioned (every direction resolved)
    rms_m: np.ndarray           # (N,) sqrt(trace(F^-1) / 3): the rms over the components; inf where unresolved


def bound_from_information(F: np.ndarray, rcond: float = RCOND) -> Bound3D:
    """cov >= F^-1 per point. A direction whose eigenvalue is at most rcond times the largest (or zero) is
    unresolved. It makes the rms and every axis that is not perpendicular to it infinite, never a number from the
    near-singular inverse."""
    F = 0.5 * (np.asarray(F, float) + np.swapaxes(np.asarray(F, float), 1, 2))
    lam, vec = np.linalg.eigh(F)                                   # ascending
    top = lam[:, -1:]
    ok = (lam > rcond * top) & (top > 0)
    inv = np.where(ok, 1.0 / np.where(ok, lam, 1.0), np.inf)       # (N, 3)
    share = vec ** 2                                               # (N, axis, direction)
    axis_var = np.where(ok[:, None, :], share * np.where(ok, inv, 0.0)[:, None, :],
                        np.where(share > PERP_TOL ** 2, np.inf, 0.0)).sum(axis=2)
    resolved = ok.all(axis=1)
    rms = np.where(resolved, np.sqrt(np.where(ok, inv, 0.0).sum(axis=1) / 3.0), np.inf)
    return Bound3D(np.sqrt(axis_var), vec[:, :, 0], np.sqrt(inv[:, 0]), resolved, rms)


@dataclass(frozen=True)
class ViewBound:
    """One view's own bound (before any 3D combination), at the points it sees: in its image plane, metres."""

    take: str
    n_points: int               # surface points it sees with texture in both image directions
    median_sigma_x_m: float     # the bound along the image's x and y at the point's depth (sigma_px z / f)
    median_sigma_y_m: float
    median_sigma_px: float      # rms of the two, in pixels
    noise: NoiseModel


@dataclass(frozen=True)
class ModeBound:
    """Per mode: the measured noise floor (NoiseFloor.mode_floor_m, at the sensors) against the floor that the
    same decay fit's gain would give noise at the bound."""

    floor_m: np.ndarray         # (R,) measured
    bound_floor_m: np.ndarray   # (R,) FLOOR_SIGMAS x the fit's white-noise gain x the bound at the sensors
    ratio: np.ndarray           # (R,) floor_m / bound_floor_m
    sensor_bound_m: np.ndarray  # (S,) the bound read through the sensors' k-neighbour plane, per timestep


def _finite_median(x: np.ndarray) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else float("nan")


def _um(x: float) -> float | None:
    """Metres to micrometres for a summary; None for NaN or inf (JSON has neither)."""
    return float(1e6 * x) if np.isfinite(x) else None


def _plain(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


@dataclass(frozen=True)
class DisplacementBound:
    """The Cramér-Rao bound of every surface point's displacement per timestep, and the measured noise floor
    against it (metres)."""

    points_m: np.ndarray            # (N, 3)
    frame: Bound3D                  # per frame: per axis, the worst direction, conditioning
    bound_m: np.ndarray             # (N,) per timestep: frame.rms_m / sqrt(frames_per_timestep); inf: unresolved
    measured_m: np.ndarray          # (N,) NoiseFloor.point_sigma_m: rms over components, per timestep
    ratio: np.ndarray               # (N,) measured_m / bound_m; NaN where the bound is infinite
    structure: np.ndarray           # (N,) bool: the points the medians are taken over
    n_views: np.ndarray             # (N,) views that see the point (in front, unoccluded, with texture)
    views: tuple[ViewBound, ...]
    single_view_m: np.ndarray       # (N,) baseline: the best single view's in-plane bound, no 3D combination
    quantisation_m: np.ndarray      # (N,) baseline: the 3D bound were the quantisation the only noise
    frames_per_timestep: int = 1
    window_px: int | None = None    # None: each point's cell
    modes: ModeBound | None = None
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def median_ratio(self) -> float:
        """The median of measured / bound over the structure's points whose bound is finite."""
        return _finite_median(self.ratio[self.structure])

    def summary(self) -> dict:
        """The figures in micrometres (JSON-safe: None for NaN and inf)."""
        s = self.structure
        ok = s & self.frame.resolved
        axis = [_um(_finite_median(self.frame.sigma_axis_m[ok, a])) for a in range(3)]
        r = self.ratio[s]
        r = r[np.isfinite(r)]
        noise = [v.noise for v in self.views]
        out = {
            "n_points": int(len(self.points_m)), "n_structure": int(s.sum()), "n_resolved": int(ok.sum()),
            "n_unresolved": int((s & ~self.frame.resolved).sum()),
            "bound_um": _um(_finite_median(self.bound_m[ok])), "bound_axis_um": axis,
            "worst_um": _um(_finite_median(self.frame.worst_sigma_m[ok])),
            "measured_um": _um(_finite_median(self.measured_m[s])), "ratio": _plain(self.median_ratio),
            "ratio_p10_p90": [float(np.percentile(r, 10)), float(np.percentile(r, 90))] if r.size else None,
            "single_view_um": _um(_finite_median(self.single_view_m[s])),
            "quantisation_um": _um(_finite_median(self.quantisation_m[ok])),
            "frames_per_timestep": self.frames_per_timestep,
            "window_px": self.window_px if self.window_px is not None else "cell",
            "median_views": float(np.median(self.n_views[s])) if s.any() else None,
            "noise": {"gain_dn_per_e": _plain(_finite_median([m.gain_dn for m in noise])),
                      "read_dn": _plain(_finite_median([m.read_dn for m in noise])),
                      "step_dn": _plain(_finite_median([m.step_dn for m in noise])),
                      "frames": min((m.n_frames for m in noise), default=0),
                      "measured": bool(noise) and all(m.measured for m in noise)},
            "views": [{"take": v.take, "n_points": v.n_points, "sigma_x_um": _um(v.median_sigma_x_m),
                       "sigma_y_um": _um(v.median_sigma_y_m), "sigma_px": _plain(v.median_sigma_px)}
                      for v in self.views],
            "modes": None, "notes": list(self.notes),
        }
        if self.modes is not None:
            m = self.modes
            out["modes"] = {"floor_um": [_um(x) for x in m.floor_m],
                            "bound_floor_um": [_um(x) for x in m.bound_floor_m], "ratio": [_plain(x) for x in m.ratio],
                            "sensor_bound_um": [_um(x) for x in m.sensor_bound_m]}
        return out


def _cell_m(points_m: np.ndarray) -> np.ndarray:
    """(N,) each point's spacing to its neighbours: the median distance to its 4 nearest (on a grid of nodes,
    the grid's spacing)."""
    n = len(points_m)
    if n < 2:
        return np.full(n, np.nan)
    k = min(5, n)
    dist, _ = cKDTree(points_m).query(points_m, k=k)
    return np.median(dist[:, 1:], axis=1)


@dataclass(frozen=True)
class _ViewInfo:
    figures: ViewBound
    F: np.ndarray           # (N, 3, 3) this view's share of the 3D information
    Fq: np.ndarray          # (N, 3, 3) the same with quantisation noise only
    seen: np.ndarray        # (N,) bool: visible with texture in at least one image direction
    single_m: np.ndarray    # (N,) its in-plane bound, rms of x and y (inf: not seen or not textured both ways)


def _view_information(rv: RestView, points_m: np.ndarray, cell_m: np.ndarray | None,
                      window_px: int | None) -> _ViewInfo:
    """One view's information about every point. The window is window_px, or each point's cell (cell_m) seen at
    its depth. Points that are occluded, behind the camera or too near the border get none."""
    K = rv.K
    cam, uv = _to_pixels(points_m, K, rv.R, rv.t)
    z = np.where(cam[:, 2] > 0, cam[:, 2], np.inf)
    f_px = float(np.sqrt(K[0, 0] * K[1, 1]))
    if window_px is not None:
        half = np.full(len(points_m), int(window_px) // 2)
    else:
        side = np.nan_to_num(cell_m * f_px / z, nan=MIN_CELL_PX)
        half = np.clip(np.rint((side - 1) / 2), MIN_CELL_PX // 2, MAX_CELL_PX // 2).astype(int)
    seen = _visible(cam, uv, rv.rest_dn.shape)
    P = projection_jacobian(points_m, K, rv.R, rv.t)
    out = []
    for quant in (False, True):
        J, inside = information_image(rv.rest_dn, rv.noise, quantisation_only=quant).window(uv, half)
        if not quant:
            seen = seen & inside
        J = resolved_2d(J)
        J[~seen] = 0.0
        out.append(J)
    J, Jq = out
    seen = seen & (np.trace(J, axis1=1, axis2=2) > 0)
    F = np.einsum("nia,nij,njb->nab", P, J, P)
    Fq = np.einsum("nia,nij,njb->nab", P, Jq, P)
    s_px = sigma_2d_px(J)
    s_m = s_px * (z[:, None] / np.array([K[0, 0], K[1, 1]]))
    both = seen & np.all(np.isfinite(s_px), axis=1)
    single = np.where(both, np.sqrt(np.mean(np.where(both[:, None], s_m, 0.0) ** 2, axis=1)), np.inf)
    figures = ViewBound(rv.take, int(both.sum()), _finite_median(s_m[both, 0]), _finite_median(s_m[both, 1]),
                        _finite_median(np.sqrt(np.mean(s_px[both] ** 2, axis=1))), rv.noise)
    return _ViewInfo(figures, F, Fq, seen, single)


def _sensor_bound(points_m: np.ndarray, F: np.ndarray, resolved: np.ndarray, sensors_m: np.ndarray,
                  sensor_dirs: np.ndarray, *, k: int, outlier_factor: float | None, scale: float, seed: int
                  ) -> np.ndarray:
    """(S,) the bound read as the analysis reads the sensors: the rms over SENSOR_DRAWS draws of noise with each
    resolved point's covariance F^-1 (times scale^2), through `SurfaceMotion.at_points`. That reading is the plane
    through the k nearest points, less outliers. Unresolved points are left out, as that reading's outlier rule
    would leave out a point that wanders."""
    pts = np.flatnonzero(resolved)
    if not len(pts) or not len(sensors_m):
        return np.full(len(sensors_m), np.nan)
    near = np.unique(cKDTree(points_m[pts]).query(sensors_m, k=min(2 * k, len(pts)))[1].ravel())
    use = pts[near]
    lam, vec = np.linalg.eigh(F[use])
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((SENSOR_DRAWS, len(use), 3)) / np.sqrt(lam)[None]
    disp = scale * np.einsum("nij,tnj->tni", vec, z)
    motion = SurfaceMotion(np.arange(SENSOR_DRAWS, dtype=float), points_m[use], disp, np.ones(len(use)), 1.0,
                           "crlb")
    read = motion.at_points(sensors_m, sensor_dirs, k=k, outlier_factor=outlier_factor)       # (D, S)
    return np.sqrt(np.mean(read ** 2, axis=0))


def mode_bound(noise: NoiseFloor, sensor_bound_m: np.ndarray) -> ModeBound:
    """Each mode's measured floor against the floor that noise at the bound would give through the same decay
    fit. The measured floor is FLOOR_SIGMAS x g_r x sqrt(spectrum_gain_r) x rms(sensor_sigma_m), with g_r the
    fit's gain for white noise; the bound's is white (each frame's noise is its own), so it is FLOOR_SIGMAS x g_r x
    rms(sensor_bound_m). The ratio is then the sensors' noise over their bound, times the measured noise's colour at
    the mode."""
    sensor_rms = float(np.sqrt(np.mean(np.asarray(noise.sensor_sigma_m, float) ** 2)))
    gain_white = noise.mode_floor_m / np.maximum(FLOOR_SIGMAS * sensor_rms * np.sqrt(noise.spectrum_gain), 1e-300)
    b = np.asarray(sensor_bound_m, float)
    b_rms = float(np.sqrt(np.mean(b ** 2))) if b.size and np.all(np.isfinite(b)) else float("nan")
    bound_floor = FLOOR_SIGMAS * gain_white * b_rms
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(bound_floor > 0, noise.mode_floor_m / bound_floor, np.nan)
    return ModeBound(np.asarray(noise.mode_floor_m, float), bound_floor, ratio, b)


def _views(capture: Capture) -> tuple[dict[str, dict], dict[str, TakeSync] | None, list[str]] | None:
    """The posed takes (with their sync where the capture has one: then the synced ones only)."""
    poses = _poses(capture)
    if poses is None:
        log.info("no displacement bound: %s not found", capture.paths.poses_json)
        return None
    synced = {t.name: t for t in load_sync(capture).ok} if capture.paths.sync_json.exists() else None
    names = [n for n in capture.take_names() if n in poses and (synced is None or n in synced)]
    if not names:
        log.info("no displacement bound: no posed%s take", " synced" if synced is not None else "")
        return None
    return poses, synced, names


def displacement_bound(capture: Capture, points_m: np.ndarray, point_sigma_m: np.ndarray, *,
                       structure: np.ndarray | None = None, noise: NoiseFloor | None = None,
                       sensors_m: np.ndarray | None = None, sensor_dirs: np.ndarray | None = None,
                       frames_per_timestep: int = 1, window_px: int | None = None, k: int = 16,
                       outlier_factor: float | None = 2.0, seed: int = 0) -> DisplacementBound | None:
    """The Cramér-Rao bound of the displacement of surface points (N, 3) from every posed take's frames at rest,
    against their measured noise floor point_sigma_m (N,) (NoiseFloor.point_sigma_m: rms over the components, per
    timestep). None when the capture has no poses or no posed take.

    structure (N,) bool: the points the medians are taken over (None: all). noise, sensors_m (S, 3) and
    sensor_dirs (S, 3): also each mode's floor against the bound (`ModeBound`), through the sensors' reading
    with k and outlier_factor, as the analysis reads them. frames_per_timestep: the frames of each view that one
    timestep's motion is estimated from. The reconstruction reads one grid frame per view per timestep, however
    many frames its step skips, so 1; were a timestep to average n frames, the bound would fall by sqrt(n).
    window_px: a fixed odd window; None: each point's cell (its spacing to its neighbours, seen at its depth)."""
    pts = np.asarray(points_m, float).reshape(-1, 3)
    sig = np.asarray(point_sigma_m, float).reshape(-1)
    if len(sig) != len(pts):
        raise InputError("displacement_bound: point_sigma_m", f"expected one per point ({len(pts)}); got {len(sig)}")
    keep = np.ones(len(pts), bool) if structure is None else np.asarray(structure, bool).reshape(-1)
    if len(keep) != len(pts):
        raise InputError("displacement_bound: structure", f"expected one flag per point ({len(pts)}); got {len(keep)}")
    if window_px is not None and (int(window_px) != window_px or window_px < 3 or window_px % 2 == 0):
        raise InputError("displacement_bound: window_px", f"expected an odd number of pixels >= 3; got {window_px}")
    if int(frames_per_timestep) != frames_per_timestep or frames_per_timestep < 1:
        raise InputError("displacement_bound: frames_per_timestep", f"expected a whole number >= 1; got "
                         f"{frames_per_timestep}")
    found = _views(capture)
    if found is None:
        return None
    poses, synced, names = found
    cell = _cell_m(pts) if window_px is None else None
    F, Fq = np.zeros((len(pts), 3, 3)), np.zeros((len(pts), 3, 3))
    n_views, single = np.zeros(len(pts), int), np.full(len(pts), np.inf)
    views = []
    for name in names:
        rv = rest_view(capture, name, poses[name], synced.get(name) if synced is not None else None)
        vi = _view_information(rv, pts, cell, window_px)
        F += vi.F
        Fq += vi.Fq
        n_views += vi.seen
        single = np.minimum(single, vi.single_m)
        views.append(vi.figures)
    frame, quant = bound_from_information(F), bound_from_information(Fq)
    scale = 1.0 / np.sqrt(int(frames_per_timestep))
    bound = frame.rms_m * scale
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(np.isfinite(bound) & (bound > 0), sig / bound, np.nan)
    notes = []
    if not all(v.noise.measured for v in views):
        notes.append("some views have fewer than 3 frames at rest: their noise is the quantisation's alone, and "
                     "their bound too low")
    modes = None
    if noise is not None and sensors_m is not None and sensor_dirs is not None:
        sb = _sensor_bound(pts, F, frame.resolved, np.asarray(sensors_m, float).reshape(-1, 3),
                           np.asarray(sensor_dirs, float).reshape(-1, 3), k=k, outlier_factor=outlier_factor,
                           scale=scale, seed=seed)
        modes = mode_bound(noise, sb)
    out = DisplacementBound(pts, frame, bound, sig, ratio, keep, n_views, tuple(views), single * scale,
                            quant.rms_m * scale, int(frames_per_timestep), window_px, modes, tuple(notes))
    _log(out)
    return out


def _log(b: DisplacementBound) -> None:
    s = b.summary()
    n = s["noise"]
    log.info("camera noise over %d views: gain %s DN/e-, read noise %s DN, step %s DN (%d frames at rest%s)",
             len(b.views), n["gain_dn_per_e"], n["read_dn"], n["step_dn"], n["frames"],
             "" if n["measured"] else "; quantisation only in some views")
    log.info("displacement bound: %s um per point and timestep (axes %s um, worst direction %s um; single view "
             "%s um; quantisation only %s um) over %d of %d structure points (%d unresolved); measured %s um, "
             "ratio %s", s["bound_um"], s["bound_axis_um"], s["worst_um"], s["single_view_um"], s["quantisation_um"],
             s["n_resolved"], s["n_structure"], s["n_unresolved"], s["measured_um"], s["ratio"])
    if b.modes is not None:
        log.info("mode floors against the bound: %s", ", ".join(
            f"{1e6 * f:.3g}/{1e6 * g:.3g} um ({r:.2f}x)" for f, g, r in zip(b.modes.floor_m, b.modes.bound_floor_m,
                                                                           b.modes.ratio)))


AXES = ("x", "y", "z")


@dataclass(frozen=True)
class DirectionFloor:
    """Each mode's video shape against a floor per point and world direction: the measured floor at the point
    (FLOOR_SIGMAS x the fit's gain x its noise), shared out over x, y and z as the bound's ellipsoid is there (a
    direction the views resolve badly gets more of it, one they cannot resolve an infinite floor)."""

    unresolved_share: np.ndarray        # (R,) share of the mode's motion power (structure's points) below its floor
    unresolved_axis_share: np.ndarray   # (R, 3) the same along each world axis, of that axis' power
    point_resolved: np.ndarray          # (R, N) bool: at the point, most of the mode's motion above its floor
    below: np.ndarray                   # (R, N, 3) bool: the mode's motion at the point along the axis is below
    axis_power_share: np.ndarray        # (R, 3) each world axis' share of the mode's motion power

    def noise_axes(self, share: float = NOISE_AXIS_SHARE) -> np.ndarray:
        """(R, 3) bool: the world axes along which at least `share` of the mode's motion power lies below the floor
        there: that component of its shape is the noise's."""
        return self.unresolved_axis_share >= share

    def lines(self, freq_hz: np.ndarray, min_share: float = 0.5, min_power: float = 0.05) -> list[str]:
        """A sentence per mode with at least min_share of its motion along some axis below that axis' floor, of the
        axes that carry at least min_power of the mode's motion (the others hardly move: nothing to read there)."""
        out = []
        for f, share, axes, power in zip(np.asarray(freq_hz, float), self.unresolved_share,
                                         self.unresolved_axis_share, self.axis_power_share):
            bad = [f"{AXES[c]} ({100 * axes[c]:.0f} %)" for c in range(3)
                   if axes[c] >= min_share and power[c] >= min_power]
            if bad:
                out.append(f"{f:.1f} Hz: its motion along {', '.join(bad)} lies below the video's floor in that "
                           f"direction ({100 * share:.0f} % of the mode's motion in all): the views do not resolve it "
                           "there; read that part from the accelerometers")
        return out


def direction_floor(bound: DisplacementBound, amplitudes_m: np.ndarray, mode_gain: np.ndarray) -> DirectionFloor:
    """Per mode and point, the video's shape (the decay fit's complex amplitudes C, (R, N, 3), motion 2|C|) against
    the floor per world axis: FLOOR_SIGMAS x mode_gain_r (the fit's gain on the point's noise, colour included)
    x the measured noise at the point, times sigma_axis / rms of the bound there (so the rms over the axes is the
    point's floor). Over the structure's points, what share of each mode's motion power lies below it."""
    amp = 2 * np.abs(np.asarray(amplitudes_m, complex))                                  # (R, N, 3)
    rms = bound.frame.rms_m
    with np.errstate(divide="ignore", invalid="ignore"):
        shape = np.where(np.isfinite(rms)[:, None], bound.frame.sigma_axis_m / rms[:, None], np.inf)   # (N, 3)
    with np.errstate(invalid="ignore"):                  # inf x 0: NaN, a floor no motion stands above
        floor = FLOOR_SIGMAS * np.asarray(mode_gain, float)[:, None, None] * bound.measured_m[None, :, None] * shape
    below = ~(amp >= floor)                                                             # NaN or inf floors: below
    s = bound.structure
    power = amp[:, s] ** 2
    total = np.maximum(power.sum(axis=(1, 2)), 1e-300)
    axis_total = np.maximum(power.sum(axis=1), 1e-300)
    point_power = np.maximum((amp ** 2).sum(axis=2), 1e-300)
    return DirectionFloor((power * below[:, s]).sum(axis=(1, 2)) / total,
                          (power * below[:, s]).sum(axis=1) / axis_total,
                          (amp ** 2 * below).sum(axis=2) / point_power < 0.5, below, axis_total / total[:, None])


def limit_lines(bound: DisplacementBound, freq_hz: np.ndarray, below_floor: np.ndarray,
                max_ratio: float = 2.0) -> list[str]:
    """What limits each mode's floor, in words: the camera (its floor within max_ratio of the bound) or what the
    pipeline adds to it (each point's noise over its bound, and the rest: the sensors' reading and the colour)."""
    if bound.modes is None:
        return []
    point = bound.median_ratio
    out = []
    for f, r, b in zip(np.asarray(freq_hz, float), bound.modes.ratio, np.asarray(below_floor, bool)):
        tag = " (below the floor)" if b else ""
        if not np.isfinite(r):
            out.append(f"{f:.1f} Hz{tag}: no bound (no view resolves the sensors' points)")
        elif r <= max_ratio:
            out.append(f"{f:.1f} Hz{tag}: floor {r:.2g} x the bound: the camera's noise limits it")
        else:
            rest = r / point if np.isfinite(point) and point > 0 else float("nan")
            out.append(f"{f:.1f} Hz{tag}: floor {r:.2g} x the bound: not the camera; each point's noise is "
                       f"{point:.2g} x its bound (the reconstruction), and reading the sensors through their "
                       f"neighbours with the noise's colour at this frequency adds {rest:.2g} x")
    return out


def physical_limit(bound: DisplacementBound, direction: DirectionFloor | None, freq_hz: np.ndarray,
                   below_floor: np.ndarray) -> dict:
    """The analysis document's record of the physical limit (JSON-safe, micrometres): the bound's summary, each
    mode's floor against the floor at the bound with what limits it, and its motion below the floor per direction."""
    out = bound.summary()
    f = np.asarray(freq_hz, float)
    limits = limit_lines(bound, f, below_floor)
    modes = []
    for r, fr in enumerate(f):
        m: dict = {"freq_hz": float(fr), "below_floor": bool(np.asarray(below_floor)[r])}
        if bound.modes is not None:
            m.update(floor_um=_um(bound.modes.floor_m[r]), bound_floor_um=_um(bound.modes.bound_floor_m[r]),
                     ratio=_plain(bound.modes.ratio[r]), limit=limits[r] if r < len(limits) else None)
        if direction is not None:
            m.update(unresolved_share=_plain(direction.unresolved_share[r]),
                     unresolved_axis_share=[_plain(x) for x in direction.unresolved_axis_share[r]])
        modes.append(m)
    out["modes"] = modes
    out["direction_lines"] = direction.lines(f) if direction is not None else []
    return out
