"""Streaming temporal filters: pass band, stop band, delay, and the same result in any chunking."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from odsplat.processing.filters import KINDS, make_filter
from odsplat.spine.errors import InputError

FPS = 2000.0
BAND = (100.0, 300.0)


def _run(flt, x: torch.Tensor, chunk: int) -> torch.Tensor:
    return torch.cat([flt(x[i:i + chunk]) for i in range(0, len(x), chunk)])


def _gain(kind: str, f_hz: float) -> float:
    t = np.arange(800) / FPS
    x = torch.tensor(np.sin(2 * np.pi * f_hz * t))[:, None, None]
    flt = make_filter(kind, FPS, *BAND)
    y = _run(flt, x, 64)[:, 0, 0].numpy()
    d = flt.delay_frames
    out, inp = y[400:], x[400 - d:800 - d, 0, 0].numpy()
    return float(np.std(out) / np.std(inp)) * float(np.sign(np.corrcoef(out, inp)[0, 1]))


@pytest.mark.parametrize("kind, pass_tol, stop_max", [("fir", 0.03, 0.01), ("ideal", 0.2, 0.03), ("butter", 0.03, 0.08),
                                                       ("diff_iir", 0.6, 0.4)])
def test_band_pass_and_stop(kind, pass_tol, stop_max):
    assert _gain(kind, 180.0) == pytest.approx(1.0, abs=pass_tol)
    for f in (20.0, 700.0):
        assert abs(_gain(kind, f)) < stop_max, (kind, f)


def test_linear_phase_filters_are_zero_phase_after_their_delay():
    t = np.arange(800) / FPS
    x = torch.tensor(np.sin(2 * np.pi * 180.0 * t))[:, None]
    for kind in ("fir", "ideal"):
        flt = make_filter(kind, FPS, *BAND)
        y = _run(flt, x, 50)[:, 0].numpy()
        d = flt.delay_frames
        assert d == (flt.min_frames - 1) // 2
        lag = np.argmax(np.correlate(y[300:700], x[300 - d - 5:700 - d + 5, 0].numpy(), "valid"))
        assert lag == 5  # aligned with the input d frames back


@pytest.mark.parametrize("kind", [k for k in KINDS])
def test_any_chunking_gives_the_same_output(kind):
    rng = np.random.default_rng(0)
    x = torch.tensor(rng.standard_normal((150, 3, 4)))
    outs = []
    for chunk in (1, 7, 150):
        flt = make_filter(kind, FPS, *BAND) if kind != "none" else make_filter(kind, FPS)
        outs.append(_run(flt, x, chunk))
    torch.testing.assert_close(outs[0], outs[2])
    torch.testing.assert_close(outs[1], outs[2])


def test_bad_bands_are_refused():
    with pytest.raises(InputError, match=r"0 < low < high < fps/2 = 1000 Hz; got 100 to 1200 Hz"):
        make_filter("butter", FPS, 100.0, 1200.0)
    with pytest.raises(InputError, match="got 0 to 300 Hz"):
        make_filter("fir", FPS, 0.0, 300.0)
    with pytest.raises(InputError, match="needs a band"):
        make_filter("fir", FPS)
    with pytest.raises(InputError, match="expected one of"):
        make_filter("gaussian", FPS, 1.0, 2.0)
