"""bench/scale.py's measurements, on small things: a child's memory and core time are measured (a process that
holds 200 MB reads at least that), and the exponents are the slopes of the figures it is given."""
from __future__ import annotations

import sys

import numpy as np


def test_a_child_that_holds_memory_and_spins_is_measured(bench_script, tmp_path):
    scale = bench_script("scale")
    code = ("import numpy as np, time\n"
            "a = np.ones(25_000_000)\n"                  # 200 MB, touched
            "t = time.process_time()\n"
            "while time.process_time() - t < 0.5: pass\n")
    m = scale.measure([sys.executable, "-c", code], tmp_path / "log")
    assert m["status"] == 0
    assert m["peak_rss_bytes"] > 200e6 and m["max_process_rss_bytes"] > 200e6, m
    assert m["core_s"] >= 0.5 and m["wall_s"] >= 0.5, m
    bad = scale.measure([sys.executable, "-c", "raise SystemExit(3)"], tmp_path / "log")
    assert bad["status"] == 3


def test_exponents_are_the_slopes_of_the_figures(bench_script):
    scale = bench_script("scale")
    rows = []
    for f in (32, 64, 128):
        st = {s: {"wall_s": 2.0 * f, "core_s": 0.5 * f ** 2, "peak_rss_bytes": 1e9} for s in scale.STAGES}
        rows.append({"frames": f, "size": "256x256", "stages": st,
                     "total": {"wall_s": 14.0 * f, "core_s": 3.5 * f ** 2, "peak_rss_bytes": 1e9}})
    fit = scale.exponents(rows, "frames")
    e = fit["exponent"]
    assert fit["values"] == [32.0, 64.0, 128.0]
    for stage in (*scale.STAGES, "total"):
        assert np.isclose(e[stage]["wall_s"], 1.0) and np.isclose(e[stage]["core_s"], 2.0)
        assert abs(e[stage]["peak_rss_bytes"]) < 1e-9
    px = scale.exponents([{**r, "size": s} for r, s in zip(rows, ("128x128", "256x128", "256x256"))], "pixels")
    assert px["values"] == [128.0 * 128, 256.0 * 128, 256.0 * 256]


def test_tree_bytes_counts_files_not_links(bench_script, tmp_path):
    scale = bench_script("scale")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "a.bin").write_bytes(b"x" * 1000)
    (tmp_path / "d" / "link").symlink_to(tmp_path / "d" / "a.bin")
    assert scale.tree_bytes(tmp_path / "d") == 1000
