"""Complex steerable pyramid built with FFTs (Portilla & Simoncelli 2000): the spatial decomposition of
phase-based motion magnification (Wadhwa et al. 2013).

Frequencies are normalised so that r = |omega| / pi is 1 at the Nyquist frequency. Radial masks are
raised cosines in log2 r, `twidth` octaves wide, with edges at r = 1, 1/2, 1/4, ...: the high-pass
residual keeps the top octave (r from 2**-twidth up), scale s is the octave band between the edges at
2**-s and 2**-(s+1), split into `n_orientations` one-sided angular sectors (complex bands, an analytic
signal along the sector's direction), and the low-pass residual keeps what is below the coarsest scale.
After each scale the spectrum is cropped to half size, so scale s lives on a grid of about
(H / 2**s, W / 2**s) pixels. With `scales_per_octave` n (Wadhwa et al.'s half- and quarter-octave
pyramids) the edges are 1/n octave apart, the transitions 1/n octave wide (`twidth` / n), and the grid is
halved once the low-pass fits the smaller one, every n scales: narrower bands, whose envelopes carry less of
the motion the phase cannot move. With `top_band` the first edge moves up an octave: the top octave becomes
a full-resolution band 0, and the high-pass residual keeps only the corners beyond Nyquist.
Orientation k passes wave vectors at angle pi * k / n_orientations from the +x (column) axis towards
the +y (row, downward) axis. The transform is a tight frame: `reconstruct` of an unmodified pyramid
returns the image up to rounding.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import torch

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

MIN_BAND_SIDE_PX = 8


def max_scales(height_px: int, width_px: int, min_side_px: int = MIN_BAND_SIDE_PX) -> int:
    """How many octave scales fit while the coarsest band keeps at least `min_side_px` on its short side."""
    n, h, w = 0, height_px, width_px
    while min(h, w) >= min_side_px:
        n += 1
        h, w = (h + 1) // 2, (w + 1) // 2
    return n


@dataclass
class SteerableCoeffs:
    """The pyramid of N images. bands[s] is (N, K, h_s, w_s) complex, s = 0 the finest scale."""

    highpass: torch.Tensor  # (N, H, W) real
    bands: list[torch.Tensor]
    lowpass: torch.Tensor  # (N, h_S, w_S) real

    def replace_bands(self, bands: list[torch.Tensor]) -> "SteerableCoeffs":
        return SteerableCoeffs(self.highpass, bands, self.lowpass)


def _crop_index(n: int) -> torch.Tensor:
    """Indices (in FFT order of a length-n spectrum) of the frequencies kept by a half-size grid, listed in
    the FFT order of that smaller grid, so that `spec[idx]` is the smaller grid's spectrum."""
    m = (n + 1) // 2
    ks = list(range(0, m - m // 2)) + list(range(-(m // 2), 0))
    return torch.tensor([k % n for k in ks], dtype=torch.long)


def _rising(log_r: torch.Tensor, edge: float, twidth: float) -> torch.Tensor:
    """Raised-cosine (amplitude: cosine) step in log2 radius: 0 below edge - twidth, 1 above edge.
    Its complement `_falling` satisfies rising**2 + falling**2 = 1, which makes the pyramid a tight frame."""
    u = ((edge - log_r) / twidth).clamp(0.0, 1.0)
    return torch.cos(0.5 * math.pi * u)


def _falling(log_r: torch.Tensor, edge: float, twidth: float) -> torch.Tensor:
    u = ((edge - log_r) / twidth).clamp(0.0, 1.0)
    return torch.sin(0.5 * math.pi * u)


class ComplexSteerablePyramid:
    """FFT steerable pyramid for images of one size; the filters are built once in `__init__`.

    `n_scales` defaults to as many octaves as keep the coarsest band at least MIN_BAND_SIDE_PX on its
    short side (plus the top band when asked for). `band_shapes[s]` is the grid of scale s.
    """

    def __init__(self, height_px: int, width_px: int, n_scales: int | None = None, n_orientations: int = 4,
                 twidth: float = 1.0, *, top_band: bool = False, scales_per_octave: int = 1,
                 device: torch.device | str | None = None):
        if height_px < 1 or width_px < 1:
            raise InputError("pyramid", f"image size must be positive, got {height_px} x {width_px}")
        if scales_per_octave not in (1, 2, 4):
            raise InputError("pyramid", f"scales_per_octave must be 1, 2 or 4, got {scales_per_octave}")
        per = int(scales_per_octave)
        fit = max_scales(height_px, width_px) * per
        # An explicit request may go coarser than the default, down to 4 px bands, not further.
        most = max(fit, max_scales(height_px, width_px, 4) * per) + int(top_band) * per
        if n_scales is None:
            n_scales = fit + int(top_band) * per if fit else 0
        if n_scales < 1 or n_scales > most:
            raise InputError("pyramid", f"{n_scales} scales do not fit a {height_px} x {width_px} image "
                                        f"(at most {most}, at least 1; images need {MIN_BAND_SIDE_PX} px "
                                        f"on their short side)")
        if not 1 <= n_orientations <= 16:
            raise InputError("pyramid", f"n_orientations must be 1 to 16, got {n_orientations}")
        if not twidth > 0:
            raise InputError("pyramid", f"twidth must be positive, got {twidth}")
        self.height_px, self.width_px = height_px, width_px
        self.n_scales, self.n_orientations, self.twidth = n_scales, n_orientations, float(twidth)
        self.scales_per_octave = per
        self.top_band = bool(top_band)
        self.device = torch.device(device) if device is not None else torch.device("cpu")
        self._build_filters()

    # The filters stay in the original image's frequency units on every cropped grid, so that odd sizes
    # (whose half-size grid is not exactly half) still reconstruct exactly.
    def _build_filters(self) -> None:
        dev, K = self.device, self.n_orientations
        fy = torch.fft.fftfreq(self.height_px, dtype=torch.float64) * 2.0  # r = 1 at Nyquist
        fx = torch.fft.fftfreq(self.width_px, dtype=torch.float64) * 2.0
        wy, wx = torch.meshgrid(fy, fx, indexing="ij")
        r = torch.sqrt(wx ** 2 + wy ** 2)
        r[0, 0] = 2.0 ** -(self.n_scales + 8)  # DC: below every band, inside every low-pass
        log_r = torch.log2(r)
        theta = torch.atan2(wy, wx)
        step = 1.0 / self.scales_per_octave   # octaves between edges
        tw = self.twidth * step

        # The first split: at Nyquist (r = 1) normally; one octave higher with a top band, so that the
        # high-pass residual keeps only the corners beyond Nyquist and the Nyquist lines, where w and -w
        # alias and a one-sided filter cannot be inverted.
        top = 1.0 if self.top_band else 0.0
        hi0, lo0 = _rising(log_r, top, tw), _falling(log_r, top, tw)
        if self.top_band:
            nyquist = torch.zeros_like(r, dtype=torch.bool)
            if self.height_px % 2 == 0:
                nyquist[self.height_px // 2, :] = True
            if self.width_px % 2 == 0:
                nyquist[:, self.width_px // 2] = True
            hi0, lo0 = torch.where(nyquist, 1.0, hi0), torch.where(nyquist, 0.0, lo0)
        self._hi0, self._lo0 = hi0.float().to(dev), lo0.float().to(dev)

        # sum_k cos(theta - pi k / K)**(2 (K - 1)) = K C(2n, n) / 4**n with n = K - 1: normalise to 1.
        order = K - 1
        gain = 2.0 ** order * math.factorial(order) / math.sqrt(K * math.factorial(2 * order))
        self._analysis: list[torch.Tensor] = []
        self._synthesis: list[torch.Tensor] = []
        self._lomask: list[torch.Tensor] = []
        self._crop: list[tuple[torch.Tensor, torch.Tensor] | None] = []
        self.band_shapes: list[tuple[int, int]] = []
        h, w = self.height_px, self.width_px
        crops = 0
        for s in range(self.n_scales):
            self.band_shapes.append((h, w))
            edge = top - (s + 1.0) * step
            himask = _rising(log_r, edge, tw)
            sectors = []
            for k in range(K):
                c = torch.cos(theta - math.pi * k / K)
                # One-sided: keep the half plane the sector points into. On its edge line (which only
                # carries energy for K = 1) w and -w are both kept, each at 1/sqrt(2) to stay a tight frame.
                on_edge = c.abs() < 1e-9  # cos(pi/2) is 6e-17, not 0
                side = ((c > 0) & ~on_edge).double() + math.sqrt(0.5) * on_edge.double()
                sectors.append(gain * c.abs() ** order * side)
            sector = torch.stack(sectors) * himask
            # Analysis doubles the one-sided filter so the band's real part is the real steerable band;
            # synthesis uses the undoubled one and takes the real part at the end.
            self._analysis.append((2.0 * sector).float().to(dev))
            self._synthesis.append(sector.float().to(dev))
            self._lomask.append(_falling(log_r, edge, tw).float().to(dev))
            if edge > -(crops + 1) + 1e-9:  # the low-pass still reaches above half this grid's Nyquist: keep it
                self._crop.append(None)
                continue
            crops += 1
            iy, ix = _crop_index(h), _crop_index(w)
            self._crop.append((iy.to(dev), ix.to(dev)))
            log_r, theta = log_r[iy][:, ix], theta[iy][:, ix]
            h, w = len(iy), len(ix)
        self.lowpass_shape = (h, w)
        log.debug("steerable pyramid %dx%d: %d scales x %d orientations, bands %s",
                  self.height_px, self.width_px, self.n_scales, K, self.band_shapes)

    def build(self, x: torch.Tensor) -> SteerableCoeffs:
        """(N, H, W) real images -> the pyramid (complex bands, real residuals)."""
        if x.ndim != 3 or tuple(x.shape[1:]) != (self.height_px, self.width_px):
            raise InputError("pyramid", f"expected images shaped (N, {self.height_px}, {self.width_px}), "
                                        f"got {tuple(x.shape)}")
        # norm="forward" keeps Fourier-series amplitudes, so the bands on every grid share the image's units.
        spec = torch.fft.fft2(x.to(self.device, torch.float32), norm="forward")
        highpass = torch.fft.ifft2(spec * self._hi0, norm="forward").real
        lo = spec * self._lo0
        bands = []
        for s in range(self.n_scales):
            bands.append(torch.fft.ifft2(lo[:, None] * self._analysis[s], norm="forward"))
            lo = lo * self._lomask[s]
            if self._crop[s] is not None:
                iy, ix = self._crop[s]
                lo = lo[:, iy][:, :, ix]
        lowpass = torch.fft.ifft2(lo, norm="forward").real
        return SteerableCoeffs(highpass, bands, lowpass)

    def reconstruct(self, coeffs: SteerableCoeffs) -> torch.Tensor:
        """The pyramid -> (N, H, W) real images. Modified complex bands contribute their one-sided part."""
        lo = torch.fft.fft2(coeffs.lowpass.to(torch.complex64), norm="forward")
        for s in reversed(range(self.n_scales)):
            if self._crop[s] is None:
                up = lo
            else:
                iy, ix = self._crop[s]
                up = torch.zeros((lo.shape[0], *self.band_shapes[s]), dtype=lo.dtype, device=lo.device)
                up[:, iy[:, None], ix[None, :]] = lo
            band_spec = torch.fft.fft2(coeffs.bands[s], norm="forward")
            lo = up * self._lomask[s] + (band_spec * self._synthesis[s]).sum(dim=1)
        spec = lo * self._lo0 + torch.fft.fft2(coeffs.highpass.to(torch.complex64), norm="forward") * self._hi0
        return torch.fft.ifft2(spec, norm="forward").real


__all__ = ["ComplexSteerablePyramid", "SteerableCoeffs", "max_scales", "MIN_BAND_SIDE_PX"]
