"""bench/phase_gain.py (issue 47's "alpha = 10 gives 8.2"): on a texture filling the frame the Eulerian phase method
falls short of alpha (its bands' envelopes do not move, its low-pass residual not at all) and the Lagrangian
synthesis (`warp`) reads alpha; its JSON line carries every variant's figures. Small data; the figures are the
bench's (docs/magnification-phase.md)."""
from __future__ import annotations

import pytest


def test_whole_frame_gain_of_the_eulerian_phase_is_short_and_the_warp_is_exact(bench_script):
    bench = bench_script("phase_gain")
    eulerian = bench.whole_frame_gain({}, "value_noise", 64, 0.1)
    assert 6.0 < eulerian < 9.5
    assert bench.whole_frame_gain({"warp": True}, "value_noise", 64, 0.1) == pytest.approx(10.0, rel=0.02)


def test_the_json_line_has_every_variant(bench_script, capsys):
    bench = bench_script("phase_gain")
    out = bench.main(["--size", "48", "--clip-size", "0", "--variants", "default,half_octave"])
    assert bench.json.loads(capsys.readouterr().out.strip().splitlines()[-1]) == out
    for name in ("default", "half_octave"):
        r = out[name]
        assert r["options"] == bench.VARIANTS[name] and sorted(r["whole_frame_gain"]) == sorted(bench.protocol.TEXTURES)
        assert all(len(v) == len(bench.DELTAS_PX) for v in r["whole_frame_gain"].values())
        assert 0 < r["whole_frame_worst_rel_err"] < 0.5
