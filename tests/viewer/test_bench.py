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
