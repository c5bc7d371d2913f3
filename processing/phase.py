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
from typing import Any

import torch

from odsplat.errors import InputError
from odsplat.processing.filters import TemporalFilter
from odsplat.processing.pyramid import ComplexSteerablePyramid, SteerableCoeffs
from odsplat.processing.streaming import StreamingMagnifier

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
    """

    def __init__(self, alpha: float, temporal: TemporalFilter | None = None, *, n_orientations: int = 4,
                 sigma_px: float = 2.0, reference: str | torch.Tensor = "first", attenuate_other: bool = False,
                 n_scales: int | None = None, twidth: float = 1.0, top_band: bool = False,
                 batch_frames: int = 8):
        if not sigma_px >= 0:
            raise InputError("sigma_px", f"the phase smoothing width must be >= 0 px, got {sigma_px}")
        self.n_orientations, self.n_scales, self.twidth, self.top_band = n_orientations, n_scales, twidth, top_band
        self.sigma_px, self.attenuate_other = float(sigma_px), bool(attenuate_other)
        self.pyramid: ComplexSteerablePyramid | None = None
        super().__init__(alpha, temporal, reference=reference, batch_frames=batch_frames)

    def _reset_state(self) -> None:
        self._prev: list[torch.Tensor] = []  # last frame's complex bands
        self._acc: list[torch.Tensor] = []  # its phase change against the reference (float64)
        self._ref_phase: list[torch.Tensor] = []

    def _setup(self, height_px: int, width_px: int, device: torch.device) -> int:
        if self.pyramid is None or (self.pyramid.height_px, self.pyramid.width_px) != (height_px, width_px):
            self.pyramid = ComplexSteerablePyramid(height_px, width_px, self.n_scales, self.n_orientations,
                                                   self.twidth, top_band=self.top_band, device=device)
            self._gauss = []
            for h, w in self.pyramid.band_shapes:
                wy = 2 * math.pi * torch.fft.fftfreq(h, device=device)
                wx = 2 * math.pi * torch.fft.rfftfreq(w, device=device)
                self._gauss.append(torch.exp(-0.5 * self.sigma_px ** 2 * (wy[:, None] ** 2 + wx[None, :] ** 2)))
        K = self.pyramid.n_orientations
        return sum(K * h * w for h, w in self.pyramid.band_shapes)

    def _init_reference(self, y_ref: torch.Tensor) -> None:
        bands = self.pyramid.build(y_ref).bands
        self._prev = [b[0] for b in bands]
        self._acc = [torch.zeros(b.shape[1:], dtype=torch.float64, device=b.device) for b in bands]
        self._ref_phase = [torch.angle(b[0]) for b in bands] if self.attenuate_other else []

    def _analyse(self, y: torch.Tensor) -> tuple[torch.Tensor, SteerableCoeffs]:
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
        out, offset = [], 0
        for s, b in enumerate(coeffs.bands):
            size = b[0].numel()
            dphi = features[:, offset:offset + size].reshape(b.shape)
            offset += size
            amp = b.abs()
            if self.sigma_px > 0:
                dphi = self._smooth(dphi, amp, s)
            if self.attenuate_other:
                out.append(torch.polar(amp, self._ref_phase[s] + self.alpha * dphi))
            else:
                out.append(b * torch.polar(torch.ones_like(dphi), (self.alpha - 1.0) * dphi))
        return self.pyramid.reconstruct(coeffs.replace_bands(out))

    def _smooth(self, dphi: torch.Tensor, amp: torch.Tensor, scale: int) -> torch.Tensor:
        # Weighting by amplitude keeps the noisy phase of near-zero coefficients from leaking into their
        # neighbours; the FFT blur is circular like the pyramid itself.
        shape = dphi.shape[-2:]
        g = self._gauss[scale]
        num = torch.fft.irfft2(torch.fft.rfft2(dphi * amp) * g, s=shape)
        den = torch.fft.irfft2(torch.fft.rfft2(amp) * g, s=shape)
        return num / den.clamp_min(1e-8)


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


__all__ = ["PhaseMagnifier", "measure_shift_px", "shift_image_px"]
