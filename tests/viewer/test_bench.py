"""bench/viewer.py prints one JSON line with the view's frames/s beside the training path's, on a small capture."""
from __future__ import annotations

import json

KEYS = ("bench", "capture", "gaussians", "structure_gaussians", "size", "threads", "viewer_threads", "fps",
        "fps_structure_only", "fps_mode", "fps_all_threads", "fps_1thread", "baseline_fps", "ratio",
        "ratio_structure_only", "target_fps", "meets_target", "load_average_1min")


def test_bench_viewer_prints_one_json_line_with_sane_figures(bench_script, captures, capsys):
    cap, floor, _ = captures
    bench = bench_script("viewer")
    assert bench.main([str(cap.root), "--min-time", "0.05", "--size", "160", "120"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    assert all(k in result for k in KEYS), sorted(set(KEYS) - set(result))
    assert result["bench"] == "viewer" and result["size"] == [160, 120]
    assert result["gaussians"] == len(floor) and result["structure_gaussians"] == int((~floor).sum())
    for key in ("fps", "fps_structure_only", "fps_mode", "fps_all_threads", "fps_1thread", "baseline_fps"):
        assert result[key] > 0, key
    assert result["viewer_threads"] in (1, result["threads"])
    assert result["ratio"] == round(result["fps"] / result["baseline_fps"], 2)
    assert result["meets_target"] == (result["fps"] >= result["target_fps"])


def test_bench_viewer_startup_times_the_command_to_its_first_frame(bench_script, captures, capsys):
    """bench/viewer_startup.py: `odsplat view` in fresh processes up to the first frame, beside the floor of
    imports any Qt viewer of a torch model pays; the figures, not their size (a busy machine is slower)."""
    cap, _, _ = captures
    out = bench_script("viewer_startup").main([str(cap.root), "--runs", "1"])
    line = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert line == out and line["bench"] == "viewer_startup" and line["runs"] == 1
    assert line["first_frame_s"] > line["floor_s"] > 0 and len(line["first_frame_s_all"]) == 1
    assert abs(line["over_floor_s"] - (line["first_frame_s"] - line["floor_s"])) <= 0.0015
