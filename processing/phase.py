"""Phase-based video motion magnification (Wadhwa et al. 2013) on a complex steerable pyramid, streamed in
bounded memory; plus a global sub-pixel shift estimator for checks.

Gain convention (the same in `eulerian.LinearMagnifier`): `alpha` is the factor on the motion itself. A
pattern that moves by d pixels comes out moving by alpha * d (alpha = 1 leaves the video as it is,
0 < alpha < 1 attenuates). The phase-based method therefore multiplies each band coefficient by
exp(i (alpha - 1) dphi), dphi being its (filtered) phase change against the reference frame; with a
temporal band-pass the motion inside the band is scaled by alpha and the rest passes unchanged
(or is removed, `attenuate_other=True`). Wu et al. and Wadhwa et al. call alpha - 1 "alpha".
"""
from __future__ import annotations

import logging
import math
from collections.abc import Iterator

import torch
import torch.nn.functional as F

from odsplat.processing.filters import TemporalFilter
from odsplat.processing.pyramid import ComplexSteerablePyramid, SteerableCoeffs
from odsplat.processing.streaming import StreamingMagnifier
from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

class PhaseMagnifier(StreamingMagnifier):
    """Phase-based magnification: output motion = alpha x input motion (see the module docstring).

    Per band of a complex steerable pyramid of Y: the phase change against the reference frame is the
    running sum of wrapped frame-to-frame phase differences (no wrap errors for any total motion); it is
    band-passed by `temporal` (None: magnify the change against the reference itself, "static" mode),
    smoothed by an amplitude-weighted Gaussian of `sigma_px` pixels of the band's own grid (so
    sigma_px * 2**s image pixels on a grid decimated s times; 0 turns it off), and the coefficient is
    turned by (alpha - 1) times it. With `attenuate_other` the coefficient's phase is the reference's plus
    alpha times the filtered change, which removes the motion outside the band. The high- and low-pass
    residuals are not magnified: by default the high-pass holds the octave below Nyquist (wavelengths
    under ~4 px); `top_band=True` makes that octave a magnified full-resolution band (for fine speckle;
    it breaks first as alpha * d approaches 1 px).

    Measured limit: the amplitude envelope of a band does not move, so on broadband texture the motion
    falls short of alpha * d, by ~13 % with 4 orientations and ~7 % with 8 (docs/magnification-phase.md).

    `warp=True` synthesises the other way (Lagrangian): the filtered phase changes of every band give a
    dense displacement field u (to first order dphi = -u . grad phi in each band; weighted least squares over
    all bands and orientations, each term weighted by its phase's inverse variance, from the amplitude and
    the frames' noise sd `noise_sd` (None: estimated from the first two frames), and summed over the
    `sigma_px` window of its scale), and the frame is resampled at x - (alpha - 1) u (quintic B-spline). Envelope,
    phase and the unmagnified residuals all move, so the gain is alpha on any texture. With
    `attenuate_other` the reference frame is resampled at x - alpha u.
    """

    def __init__(self, alpha: float, temporal: TemporalFilter | None = None, *, n_orientations: int = 4,
                 sigma_px: float = 2.0, reference: str | torch.Tensor = "first", attenuate_other: bool = False,
                 n_scales: int | None = None, twidth: float = 1.0, top_band: bool = False, warp: bool = False,
                 noise_sd: float | None = None, scales_per_octave: int = 1, batch_frames: int = 8):
        if not sigma_px >= 0:
            raise InputError("sigma_px", f"the phase smoothing width must be >= 0 px, got {sigma_px}")
        self.n_orientations, self.n_scales, self.twidth, self.top_band = n_orientations, n_scales, twidth, top_band
        self.scales_per_octave = scales_per_octave
        self.sigma_px, self.attenuate_other, self.warp = float(sigma_px), bool(attenuate_other), bool(warp)
        if noise_sd is not None and not noise_sd >= 0:
            raise InputError("noise_sd", f"the frames' noise sd must be >= 0 (in [0, 1] units) or None "
                                         f"(estimated), got {noise_sd}")
        self.noise_sd = None if noise_sd is None else float(noise_sd)
        self.pyramid: ComplexSteerablePyramid | None = None
        super().__init__(alpha, temporal, reference=reference, batch_frames=batch_frames)

    def _reset_state(self) -> None:
        self._prev: list[torch.Tensor] = []  # last frame's complex bands
        self._acc: list[torch.Tensor] = []  # its phase change against the reference (float64)
        self._ref_phase: list[torch.Tensor] = []
        self._ref_bands: list[torch.Tensor] = []  # warp + attenuate_other: the reference's bands and luminance
        self._ref_y: torch.Tensor | None = None
        self._first_y: torch.Tensor | None = None  # warp: the first frame, until the noise is estimated
        self._noise_est: float | None = None

    def _setup(self, height_px: int, width_px: int, device: torch.device) -> int:
        if self.pyramid is None or (self.pyramid.height_px, self.pyramid.width_px) != (height_px, width_px):
            self.pyramid = ComplexSteerablePyramid(height_px, width_px, self.n_scales, self.n_orientations,
                                                   self.twidth, top_band=self.top_band,
                                                   scales_per_octave=self.scales_per_octave, device=device)
            self._gauss = []
            for h, w in self.pyramid.band_shapes:
                wy = 2 * math.pi * torch.fft.fftfreq(h, device=device)
                wx = 2 * math.pi * torch.fft.rfftfreq(w, device=device)
                self._gauss.append(torch.exp(-0.5 * self.sigma_px ** 2 * (wy[:, None] ** 2 + wx[None, :] ** 2)))
            if self.warp:
                self._setup_warp(height_px, width_px, device)
        K = self.pyramid.n_orientations
        return sum(K * h * w for h, w in self.pyramid.band_shapes)

    def _setup_warp(self, height_px: int, width_px: int, device: torch.device) -> None:
        # Derivatives on each band's own grid (the bands are one-sided: their Nyquist rows carry nothing).
        self._d_ops = [(1j * 2 * math.pi * torch.fft.fftfreq(w, device=device)[None, :],
                        1j * 2 * math.pi * torch.fft.fftfreq(h, device=device)[:, None])
                       for h, w in self.pyramid.band_shapes]
        # Each band's noise variance per unit image noise variance: white noise through its filter.
        noise = torch.randn((4, height_px, width_px), generator=torch.Generator().manual_seed(0)).to(device)
        self._band_noise = [float(b.abs().pow(2).mean()) for b in self.pyramid.build(noise).bands]
        self._pixel_y, self._pixel_x = torch.meshgrid(torch.arange(height_px, dtype=torch.float32, device=device),
                                                      torch.arange(width_px, dtype=torch.float32, device=device),
                                                      indexing="ij")

    def _band_phases(self, features: torch.Tensor, coeffs: SteerableCoeffs
                     ) -> Iterator[tuple[int, torch.Tensor, torch.Tensor]]:
        """(scale, its bands (n, K, h, w), their filtered phase changes, the same shape), scale by scale."""
        offset = 0
        for s, b in enumerate(coeffs.bands):
            size = b[0].numel()
            yield s, b, features[:, offset:offset + size].reshape(b.shape)
            offset += size

    def _init_reference(self, y_ref: torch.Tensor) -> None:
        bands = self.pyramid.build(y_ref).bands
        self._prev = [b[0] for b in bands]
        self._acc = [torch.zeros(b.shape[1:], dtype=torch.float64, device=b.device) for b in bands]
        self._ref_phase = [torch.angle(b[0]) for b in bands] if self.attenuate_other else []
        if self.warp and self.attenuate_other:
            self._ref_bands, self._ref_y = [b[:1] for b in bands], y_ref

    @property
    def frame_noise_sd(self) -> float | None:
        """The frames' noise sd that the warp weighs with: `noise_sd` if given, else the estimate from the
        first two frames of the stream (None until two have been pushed)."""
        return self.noise_sd if self.noise_sd is not None else self._noise_est

    def _estimate_noise(self, y: torch.Tensor) -> None:
        """The frames' noise sd from the first two frames pushed: the median absolute deviation of their
        difference (a moving structure covers a small part of the frame), over sqrt(2)."""
        frames = y if self._first_y is None else torch.cat([self._first_y[None], y])
        if frames.shape[0] < 2:
            self._first_y = frames[0].clone()
            return
        diff = (frames[1] - frames[0]).flatten().double()
        self._noise_est = float((diff - diff.median()).abs().median()) / 0.6745 / math.sqrt(2.0)
        self._first_y = None
        log.debug("phase warp: frame noise sd estimated at %.2e", self._noise_est)

    def _analyse(self, y: torch.Tensor) -> tuple[torch.Tensor, SteerableCoeffs]:
        if self.warp and self.noise_sd is None and self._noise_est is None:
            self._estimate_noise(y)
        coeffs = self.pyramid.build(y)
        n = y.shape[0]
        features = []
        for s, b in enumerate(coeffs.bands):
            prev = torch.cat([self._prev[s][None], b[:-1]])
            # Each step is far below pi, so its wrapped angle is the true one; their sum never wraps.
            step = torch.angle(b * prev.conj()).double()
            acc = self._acc[s] + torch.cumsum(step, dim=0)
            self._prev[s], self._acc[s] = b[-1].clone(), acc[-1].clone()
            features.append(acc.reshape(n, -1).float())
        return torch.cat(features, dim=1), coeffs

    def _synthesise(self, y: torch.Tensor, features: torch.Tensor, cache: SteerableCoeffs | None) -> torch.Tensor:
        coeffs = cache if cache is not None else self.pyramid.build(y)
        if self.warp:
            return self._warp(y, features, coeffs)
        out = []
        for s, b, dphi in self._band_phases(features, coeffs):
            amp = b.abs()
            if self.sigma_px > 0:
                dphi = self._smooth(dphi, amp, s)
            if self.attenuate_other:
                out.append(torch.polar(amp, self._ref_phase[s] + self.alpha * dphi))
            else:
                out.append(b * torch.polar(torch.ones_like(dphi), (self.alpha - 1.0) * dphi))
        return self.pyramid.reconstruct(coeffs.replace_bands(out))

    def _warp(self, y: torch.Tensor, features: torch.Tensor, coeffs: SteerableCoeffs) -> torch.Tensor:
        """Resample the frames (or the reference) along the displacement field that the phases measure."""
        n, (H, W) = y.shape[0], y.shape[-2:]
        # The least-squares normal equations of u (image px) summed over scales, each brought to full size:
        # [mxx, mxy, myy] u = [bx, by].
        normal = torch.zeros((n, 5, H, W), dtype=torch.float32, device=y.device)
        for s, b, dphi in self._band_phases(features, coeffs):
            if self.attenuate_other:
                b = self._ref_bands[s]
            terms = self._normal_terms(b, dphi, s)
            h, w = b.shape[-2:]
            # A displacement of u_s band px is u_s * W / w image px: the matrix scales by (w / W)^2, b by w / W.
            f = w / W
            terms = terms * torch.tensor([f * f, f * f, f * f, f, f], device=y.device)[:, None, None]
            if (h, w) != (H, W):
                terms = F.interpolate(terms, size=(H, W), mode="bilinear", align_corners=False)
            normal += terms
        mxx, mxy, myy, bx, by = normal.unbind(1)
        # A floor keeps textureless regions (no phase evidence) still.
        floor = 1e-6 * (mxx + myy).mean(dim=(-2, -1), keepdim=True) + 1e-20
        mxx, myy = mxx + floor, myy + floor
        det = mxx * myy - mxy * mxy
        ux, uy = (myy * bx - mxy * by) / det, (mxx * by - mxy * bx) / det
        gain = self.alpha if self.attenuate_other else self.alpha - 1.0
        src = self._ref_y.expand(n, -1, -1) if self.attenuate_other else y
        return spline_sample(src, self._pixel_x - gain * ux, self._pixel_y - gain * uy)

    def _normal_terms(self, b: torch.Tensor, dphi: torch.Tensor, scale: int) -> torch.Tensor:
        """(n, 5, h, w): the scale's weighted least-squares terms [mxx, mxy, myy, bx, by] of dphi_k = -u . grad phi_k
        over its orientations k (u in band px), each weighted by its phase's inverse variance (A_k^2 over the
        band's noise variance, faded out near the noise) and summed over the sigma_px window."""
        dx_op, dy_op = self._d_ops[scale]
        spec = torch.fft.fft2(b)
        # Im(conj(c) grad c) = A^2 grad phi, so A^2 (grad phi)(grad phi)^T = q q^T / A^2 with q = Im(conj(c) grad c).
        qx = (b.conj() * torch.fft.ifft2(spec * dx_op)).imag
        qy = (b.conj() * torch.fft.ifft2(spec * dy_op)).imag
        a2 = (b.real ** 2 + b.imag ** 2).clamp_min(1e-12)
        noise_sd = self.frame_noise_sd or 0.0
        if noise_sd > 0:
            # Weight A^2 / var_c where the coefficient stands clear of the noise (var_c its noise variance),
            # fading to 0 at A^2 = 2 var_c: pure-noise coefficients have random phases, not small ones.
            var_c = noise_sd ** 2 * self._band_noise[scale]
            wrel = (a2 - 2.0 * var_c).clamp_min(0.0) / (a2 * var_c)
            qx, qy = qx * wrel.sqrt(), qy * wrel.sqrt()
            dphi = dphi * wrel.sqrt()
        n = dphi.shape[0]
        terms = torch.stack([(qx * qx / a2).sum(1).expand(n, -1, -1), (qx * qy / a2).sum(1).expand(n, -1, -1),
                             (qy * qy / a2).sum(1).expand(n, -1, -1), -(qx * dphi).sum(1), -(qy * dphi).sum(1)],
                            dim=1)
        if self.sigma_px > 0:
            terms = torch.fft.irfft2(torch.fft.rfft2(terms) * self._gauss[scale], s=terms.shape[-2:])
        return terms

    def _smooth(self, dphi: torch.Tensor, amp: torch.Tensor, scale: int) -> torch.Tensor:
        # Weighting by amplitude keeps the noisy phase of near-zero coefficients from leaking into their
        # neighbours; the FFT blur is circular like the pyramid itself.
        shape = dphi.shape[-2:]
        g = self._gauss[scale]
        num = torch.fft.irfft2(torch.fft.rfft2(dphi * amp) * g, s=shape)
        den = torch.fft.irfft2(torch.fft.rfft2(amp) * g, s=shape)
        return num / den.clamp_min(1e-8)


def _bspline5_pairs(t: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The quintic B-spline's six weights at taps -2..3 around a point t in [0, 1) past a sample, merged into
    three pairs: (offsets from the sample, weights) such that w_a c[k] + w_b c[k + 1] = (w_a + w_b) times c read
    linearly at k + w_b / (w_a + w_b). The weights are positive, so every pair is a proper linear read."""
    s = 1.0 - t

    def p5(u: torch.Tensor) -> torch.Tensor:
        u2 = u * u
        return u2 * u2 * u

    s0, s1, t0, t1 = p5(s), p5(1 + s), p5(t), p5(1 + t)
    w = [s0, s1 - 6 * s0, p5(2 + s) - 6 * s1 + 15 * s0, p5(2 + t) - 6 * t1 + 15 * t0, t1 - 6 * t0, t0]   # x 120
    offsets, weights = [], []
    for m in range(3):
        a, b = w[2 * m], w[2 * m + 1]
        total = a + b
        offsets.append(2 * m - 2 + b / total)
        weights.append(total / 120.0)
    return offsets, weights


SPLINE_PAD_PX = 12  # the mirrored margin: the prefilter's ringing from the wrap decays as 0.43^n


def spline_sample(img: torch.Tensor, x_px: torch.Tensor, y_px: torch.Tensor) -> torch.Tensor:
    """Sample (N, H, W) images at pixel coordinates (N, H, W) (x along columns) by quintic B-spline
    interpolation: the images are mirrored by SPLINE_PAD_PX at the borders, prefiltered by FFT into spline
    coefficients (so integer positions give the pixels back exactly), and the 6 x 6 coefficients around each
    point are weighed by the spline, as 3 x 3 bilinear reads of merged pairs (one `grid_sample`); beyond the
    margin the borders are clamped.

    Shifting texture as fine as 3 px: 0.99 of a 0.05-0.5 px shift comes out. Keys' cubic convolution
    (a = -0.5) gives 0.70 at 0.05 px and the cubic B-spline 0.95; OpenCV's and torch's bicubic (a = -0.75)
    are worse still, and shift even a smooth texture by 0.135 px for 0.1 px."""
    n, h, w = img.shape
    p = min(SPLINE_PAD_PX, h - 1, w - 1)
    padded = F.pad(img[:, None], (p, p, p, p), mode="reflect")[:, 0] if p > 0 else img
    hp, wp = padded.shape[-2:]
    wy = 2 * math.pi * torch.fft.fftfreq(hp, device=img.device, dtype=torch.float64)
    wx = 2 * math.pi * torch.fft.rfftfreq(wp, device=img.device, dtype=torch.float64)

    def response(o: torch.Tensor) -> torch.Tensor:     # the quintic B-spline sampled at the integers, as a DFT
        return (66 + 52 * torch.cos(o) + 2 * torch.cos(2 * o)) / 120

    coef = torch.fft.irfft2(torch.fft.rfft2(padded.to(x_px.dtype)) / (response(wy)[:, None] * response(wx)[None, :]
                                                                      ).to(x_px.dtype), s=(hp, wp))
    x, y = x_px + p, y_px + p
    x0, y0 = torch.floor(x), torch.floor(y)
    ox, gx = _bspline5_pairs(x - x0)
    oy, gy = _bspline5_pairs(y - y0)
    # The 9 reads as one grid_sample: grids stacked along the rows, coordinates normalised (align_corners).
    grid = torch.empty((n, 3, 3, h, w, 2), dtype=x_px.dtype, device=x_px.device)
    for m in range(3):
        grid[:, :, m, ..., 0] = ((x0 + ox[m]) * (2.0 / (wp - 1)) - 1.0)[:, None]
        grid[:, m, :, ..., 1] = ((y0 + oy[m]) * (2.0 / (hp - 1)) - 1.0)[:, None]
    reads = F.grid_sample(coef[:, None], grid.reshape(n, 9 * h, w, 2), mode="bilinear", padding_mode="border",
                          align_corners=True).reshape(n, 3, 3, h, w)
    out = torch.zeros_like(x_px)
    for j in range(3):
        out += gy[j] * (gx[0] * reads[:, j, 0] + gx[1] * reads[:, j, 1] + gx[2] * reads[:, j, 2])
    return out


def shift_image_px(img: torch.Tensor, dx_px: float, dy_px: float) -> torch.Tensor:
    """Translate (..., H, W) images by (dx, dy) pixels (x along columns, y along rows) with an FFT phase
    ramp: exact for periodic, band-limited images."""
    h, w = img.shape[-2:]
    wy = 2 * math.pi * torch.fft.fftfreq(h, dtype=torch.float64)
    wx = 2 * math.pi * torch.fft.fftfreq(w, dtype=torch.float64)
    ramp = torch.exp(-1j * (wx[None, :] * dx_px + wy[:, None] * dy_px))
    out = torch.fft.ifft2(torch.fft.fft2(img.double()) * ramp).real
    return out.to(img.dtype)


def measure_shift_px(ref: torch.Tensor, img: torch.Tensor, *, iterations: int = 10,
                     border_px: int = 0) -> tuple[float, float]:
    """Global translation (dx, dy) in pixels that best maps `ref` onto `img` (img(x) ~ ref(x - d)), by
    Gauss-Newton least squares with FFT warping; `border_px` leaves a margin out of the fit (non-periodic
    images). Accurate to ~1e-4 px on periodic band-limited images, for shifts up to a few pixels."""
    ref, img = torch.as_tensor(ref).double(), torch.as_tensor(img).double()
    if ref.ndim != 2 or ref.shape != img.shape:
        raise InputError("measure_shift_px", f"expected two (H, W) images of one size, got "
                                             f"{tuple(ref.shape)} and {tuple(img.shape)}")
    h, w = ref.shape
    wy = 2 * math.pi * torch.fft.fftfreq(h, dtype=torch.float64)[:, None]
    wx = 2 * math.pi * torch.fft.fftfreq(w, dtype=torch.float64)[None, :]
    # Derivatives of the Nyquist row/column are ambiguous; leave them out.
    dy_op = 1j * wy * (torch.arange(h)[:, None] != h // 2 if h % 2 == 0 else 1)
    dx_op = 1j * wx * (torch.arange(w)[None, :] != w // 2 if w % 2 == 0 else 1)
    spec = torch.fft.fft2(ref)
    weight = torch.zeros_like(ref)
    weight[border_px:h - border_px, border_px:w - border_px] = 1.0
    d = torch.zeros(2, dtype=torch.float64)
    for _ in range(iterations):
        warped_spec = spec * torch.exp(-1j * (wx * d[0] + wy * d[1]))
        warped = torch.fft.ifft2(warped_spec).real
        # d/dd of ref(x - d) is minus the gradient of the warped image.
        jac = torch.stack([-torch.fft.ifft2(warped_spec * dx_op).real, -torch.fft.ifft2(warped_spec * dy_op).real])
        resid = (img - warped) * weight
        a = torch.einsum("ihw,jhw->ij", jac * weight, jac)
        b = torch.einsum("ihw,hw->i", jac, resid)
        step = torch.linalg.solve(a, b)
        d = d + step
        if float(step.abs().max()) < 1e-7:
            break
    return float(d[0]), float(d[1])


__all__ = ["PhaseMagnifier", "spline_sample", "measure_shift_px", "shift_image_px"]
