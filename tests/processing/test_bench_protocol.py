"""bench/magnify_protocol.py (issue 47's measure): its pairs are exact by construction and its motion measure reads
them back; a magnifier in its linear regime reads alpha x delta; its JSON line carries every figure, on small data."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("kind", ["speckle", "value_noise", "edges"])
def test_the_pairs_are_exact_moves_and_the_measure_reads_them(bench_script, kind):
    bench = bench_script("magnify_protocol")
    img = bench.texture(kind, 96, seed=3)
    assert 0.1 - 1e-9 <= img.min() and img.max() <= 0.9 + 1e-9
    # a whole-pixel move of a periodic image is a roll: the Fourier ramp reproduces it to rounding
    assert np.allclose(bench.shifted(img, 3.0), np.roll(img, 3, axis=1), atol=1e-9)
    for dx in (0.3, 2.7, 10.0):
        assert bench.measured_motion_px(img, bench.shifted(img, dx)) == pytest.approx(dx, abs=0.05)


def test_the_textbook_magnifier_reads_alpha_delta_where_it_is_linear(bench_script):
    """Intensity Eulerian magnification is exact to first order in alpha x delta: at 0.2 px of output motion on the
    smooth texture it reads within 10 %; at the protocol's 10 px it cannot (the field's point)."""
    bench = bench_script("magnify_protocol")
    img = bench.texture("value_noise", 96, seed=1)
    small = bench.score("textbook", 0.1, 2.0, img)
    assert small["motion_px"] == pytest.approx(0.2, rel=0.1) and small["ssim"] > 0.99
    large = bench.score("textbook", 1.0, 10.0, img)
    assert large["motion_px"] < 0.8 * 10.0


def test_the_json_line_has_every_figure(bench_script, capsys):
    bench = bench_script("magnify_protocol")
    out = bench.main(["--size", "64", "--methods", "textbook,phase", "--textures", "value_noise"])
    printed = capsys.readouterr().out.strip().splitlines()[-1]
    assert bench.json.loads(printed) == out
    for m in ("textbook", "phase"):
        r = out[m]
        assert sorted(r["subpixel"]) == sorted(f"delta_{d:g}" for d in bench.DELTAS_PX)
        assert sorted(r["noise"]) == sorted(f"sigma_{s:g}" for s in bench.NOISE_SIGMAS)
        for d in bench.DELTAS_PX:
            v = r["subpixel"][f"delta_{d:g}"]
            assert v["alpha"] * d == pytest.approx(bench.OUTPUT_MOTION_PX)
            assert -1 <= v["ssim"] <= 1 and np.isfinite(v["motion_px"])
        assert r["worst_motion_rel_err"] == max(abs(v["motion_rel_err"]) for v in r["subpixel"].values())
