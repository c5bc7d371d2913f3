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


def test_a_binned_copy_is_the_same_capture_at_a_lower_resolution(bench_script, tmp_path):
    """Issue 44's comparison of resolutions: every frame binned 2 x 2 (the mean, rounded), the signals, trigger and
    QC as recorded, the intrinsics scaled; sync times the copy as it times the original."""
    from click.testing import CliRunner

    from odsplat.app.cli import main
    from odsplat.spine.store import Capture
    from odsplat.sync import SyncSettings, sync_capture

    scale = bench_script("scale")
    src = tmp_path / "full"
    r = CliRunner().invoke(main, ["capture", str(src), "--sim", "--auto", "--no-window", "--views", "2",
                                  "--frames", "24", "--size", "256x192", "--pretrigger-frames", "4"])
    assert r.exit_code == 0, r.output
    dst = scale.binned_copy(src, tmp_path / "half", 2)
    a, b = Capture.open(src), Capture.open(dst)
    assert (b.manifest.camera.width_px, b.manifest.camera.height_px) == (128, 96)
    ka, kb = a.manifest.camera.intrinsics, b.manifest.camera.intrinsics
    assert kb.fx_px == ka.fx_px / 2 and kb.cx_px == (ka.cx_px + 0.5) / 2 - 0.5
    assert a.take_names() == b.take_names() and b.id != a.id
    for name in a.take_names():
        with a.open_take(name) as ra, b.open_take(name) as rb:
            full = ra.read_frames().astype(float)
            want = np.rint(full.reshape(len(full), 96, 2, 128, 2).mean(axis=(2, 4)))
            np.testing.assert_array_equal(rb.read_frames(), want)
            np.testing.assert_array_equal(rb.frame_times_s, ra.frame_times_s)
            for ch in ra.channel_names:
                np.testing.assert_array_equal(rb.channel(ch), ra.channel(ch))
            assert rb.trigger == ra.trigger and rb.qc == ra.qc and rb.attrs["hammer_peak_force_n"] == \
                ra.attrs["hammer_peak_force_n"]
    settings = SyncSettings(write_frames=False)
    sa, sb = sync_capture(a, settings, progress=False), sync_capture(b, settings, progress=False)
    assert [t.name for t in sb.ok] == [t.name for t in sa.ok] and len(sa.ok) == 2
    for ta, tb in zip(sa.ok, sb.ok):
        assert abs(ta.offset_s - tb.offset_s) < 0.05 / sa.fps
