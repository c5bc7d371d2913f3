"""Issue 44: a stage that streams holds the same memory whatever the record's length. Two captures of the same rig,
64 and 512 frames, run by `odsplat run` stage by stage, each in its own process, with sync's working budget below
one take's frames and its takes timed in its own process (a pool's short-lived workers make the sampled peak a
matter of luck): the peak resident memory of the whole process tree (bench/scale.py's measure) of sync, and of
magnify reading sync's aligned frames (computed from the raw take as they are read), is the same within 20 %. Sync
holding a take whole in its image timing (`BUDGET_MB = "4096"`: 512 frames of 256 x 192 px in float64) fails it,
at about 720 against 250 MB."""
from __future__ import annotations

import sys

from click.testing import CliRunner

from odsplat.app.cli import main

BUDGET_MB = "16"     # a band of 256 x 192 px frames per take


def test_sync_and_magnify_peak_memory_is_flat_in_the_number_of_frames(tmp_path, bench_script):
    scale = bench_script("scale")
    peaks: dict[str, dict[int, int]] = {"sync": {}, "magnify": {}}
    for frames in (64, 512):
        out = tmp_path / f"f{frames}"
        r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", "--views", "2",
                                      "--frames", str(frames), "--size", "256x192", "--pretrigger-frames", "8"])
        assert r.exit_code == 0, r.output
        for stage in peaks:
            m = scale.measure([sys.executable, "-m", "odsplat", "run", str(out), "--from", stage, "--to", stage,
                               "--set", "sync.max_memory_mb=" + BUDGET_MB, "--set", "sync.workers=1"],
                              tmp_path / "log")
            assert m["status"] == 0, (tmp_path / "log").read_text()[-2000:]
            peaks[stage][frames] = m["peak_rss_bytes"]
    for stage, peak in peaks.items():
        assert peak[512] <= 1.2 * peak[64], (stage, {k: v / 1e6 for k, v in peak.items()})
