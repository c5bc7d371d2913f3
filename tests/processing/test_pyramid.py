"""The complex steerable pyramid: exact reconstruction, complex (analytic) bands, orientation selectivity."""
from __future__ import annotations

import math

import pytest
import torch

from odsplat.processing.pyramid import ComplexSteerablePyramid, max_scales
from odsplat.spine.errors import InputError


def _grating(h: int, w: int, cycles_x: float, cycles_y: float) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    return (0.5 + 0.2 * torch.cos(2 * math.pi * (cycles_x * x / w + cycles_y * y / h))).float()


@pytest.mark.parametrize("h,w,k,twidth,top", [(128, 128, 4, 1.0, False), (64, 96, 4, 1.0, False),
                                              (65, 77, 3, 1.0, False), (33, 40, 1, 1.0, False),
                                              (100, 100, 8, 0.5, False), (48, 48, 2, 2.0, False),
                                              (64, 96, 4, 1.0, True), (65, 77, 1, 1.0, True)])
def test_unmodified_pyramid_reconstructs_the_image(h, w, k, twidth, top):
    torch.manual_seed(1)
    pyr = ComplexSteerablePyramid(h, w, n_orientations=k, twidth=twidth, top_band=top)
    x = torch.rand(3, h, w)
    coeffs = pyr.build(x)
    err = float((pyr.reconstruct(coeffs) - x).norm() / x.norm())
    assert err < 1e-4, err
    assert len(coeffs.bands) == pyr.n_scales
    for s, b in enumerate(coeffs.bands):
        assert b.is_complex() and tuple(b.shape) == (3, k, *pyr.band_shapes[s])


@pytest.mark.parametrize("per,top", [(2, False), (4, False), (2, True)])
def test_half_and_quarter_octave_pyramids_reconstruct_and_halve_the_grid_every_octave(per, top):
    """Wadhwa et al.'s finer pyramids: `per` scales an octave, each as narrow; still a tight frame; the grid halves
    once an octave (after every `per` scales), and the coarsest band is as coarse as the octave pyramid's."""
    torch.manual_seed(2)
    pyr = ComplexSteerablePyramid(67, 96, scales_per_octave=per, top_band=top)
    octave = ComplexSteerablePyramid(67, 96, top_band=top)
    assert pyr.n_scales == per * octave.n_scales and pyr.lowpass_shape == octave.lowpass_shape
    assert pyr.band_shapes[::per] == octave.band_shapes
    x = torch.rand(2, 67, 96)
    assert float((pyr.reconstruct(pyr.build(x)) - x).norm() / x.norm()) < 1e-4
    with pytest.raises(InputError, match="scales_per_octave"):
        ComplexSteerablePyramid(64, 64, scales_per_octave=3)


def test_default_scales_stop_at_8_px_bands():
    assert max_scales(128, 128) == 5  # bands 128, 64, 32, 16, 8
    assert ComplexSteerablePyramid(64, 96).band_shapes == [(64, 96), (32, 48), (16, 24), (8, 12)]
    # The top band (the octave below Nyquist) is one more band on the full grid.
    assert ComplexSteerablePyramid(64, 96, top_band=True).band_shapes == [(64, 96), (64, 96), (32, 48), (16, 24),
                                                                          (8, 12)]
    with pytest.raises(InputError, match="scales do not fit"):
        ComplexSteerablePyramid(64, 64, n_scales=9)
    with pytest.raises(InputError, match="8 px"):
        ComplexSteerablePyramid(6, 64)


def test_bands_are_analytic_and_orientations_select_their_direction():
    n, K = 128, 4
    pyr = ComplexSteerablePyramid(n, n, n_orientations=K)
    # About 16 cycles / 128 px: r = 0.25, at the centre of scale 1's pass band.
    # Wave vectors at 0, 45, 90 and 135 degrees from +x towards +y (rows), on grid frequencies.
    for k, (cx, cy) in enumerate([(16, 0), (12, 12), (0, 16), (-12, 12)]):
        img = _grating(n, n, cx, cy)
        band = pyr.build(img[None]).bands[1][0]
        energy = band.abs().pow(2).mean(dim=(-2, -1))
        assert int(energy.argmax()) == k, (k, energy)
        # The other orientations are well below (cos^3 sectors: at 45 degrees off, 1/4 of the energy or less).
        others = torch.cat([energy[:k], energy[k + 1:]])
        assert float(others.max() / energy[k]) < 0.3
        # Analytic: a grating's complex band has a constant modulus (a real band would swing to zero).
        mod = band[k].abs()
        assert float(mod.std() / mod.mean()) < 1e-3


def test_band_phase_advances_along_the_orientation():
    n = 64
    pyr = ComplexSteerablePyramid(n, n)
    band = pyr.build(_grating(n, n, 8, 0)[None]).bands[1][0, 0]  # wave along +x, scale 1 (r = 0.25)
    step = torch.angle(band[:, 1:] * band[:, :-1].conj())
    # Scale 1 lives on a 32 px grid: the phase grows by 2 pi * 8 / 32 per band pixel along +x, positive
    # (one-sided: positive frequencies only).
    assert pyr.band_shapes[1] == (32, 32)
    assert float((step - 2 * math.pi * 8 / 32).abs().max()) < 1e-4


def test_wrong_image_size_is_an_input_error():
    pyr = ComplexSteerablePyramid(32, 32)
    with pytest.raises(InputError, match=r"\(N, 32, 32\)"):
        pyr.build(torch.zeros(1, 32, 31))


def test_top_band_takes_the_octave_below_nyquist_from_the_high_pass():
    n = 64
    img = _grating(n, n, 24, 0)[None]  # r = 0.75: in the high-pass residual of the standard pyramid
    std, top = ComplexSteerablePyramid(n, n).build(img), ComplexSteerablePyramid(n, n, top_band=True).build(img)
    ac = float((img - img.mean()).pow(2).mean())
    assert float(std.highpass.pow(2).mean()) > 0.5 * ac
    assert float(top.highpass.pow(2).mean()) < 1e-10
    mod = top.bands[0][0, 0].abs()  # analytic there too
    assert float(mod.std() / mod.mean()) < 1e-3
