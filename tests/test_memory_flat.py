"""Issue 44: a stage that streams holds the same memory whatever the record's length. Two captures of the same rig,
64 and 512 frames, synced by `odsplat run` in its own process with a working budget below one take's frames: the
peak resident memory of the whole process tree (bench/scale.py's measure) is the same within 20 %. Sync holding a
take whole (512 frames of 256 x 192 px in float64, and the FFT's copies) would add about 1 GB at 512 frames."""
from __future__ import annotations

import sys

from click.testing import CliRunner

from odsplat.app.cli import main

BUDGET_MB = "16"     # a band of 256 x 192 px frames per take; 4096 (every take whole) fails this test


def test_sync_peak_memory_is_flat_in_the_number_of_frames(tmp_path, bench_script):
    scale = bench_script("scale")
    peaks = {}
    for frames in (64, 512):
        out = tmp_path / f"f{frames}"
        r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", "--views", "2",
                                      "--frames", str(frames), "--size", "256x192", "--pretrigger-frames", "8"])
        assert r.exit_code == 0, r.output
        m = scale.measure([sys.executable, "-m", "odsplat", "run", str(out), "--to", "sync",
                           "--set", "sync.max_memory_mb=" + BUDGET_MB], tmp_path / "log")
        assert m["status"] == 0, (tmp_path / "log").read_text()[-2000:]
        peaks[frames] = m["peak_rss_bytes"]
    assert peaks[512] <= 1.2 * peaks[64], {k: v / 1e6 for k, v in peaks.items()}
