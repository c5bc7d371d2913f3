"""Beyond our own rig's defaults (issue 30): a 27-view capture at 256x256 px with 12-bit frames in 16-bit words,
a procedural texture and floor tags 15-19 px wide is synced and posed whole with the defaults.

The plate the defaults were not tuned to, captured and run whole and scored against its analytic modes, is
bench/fidelity.py's (`--cases plate_600n`: the 8-view plate hit at 600 N that was this file's test, 2-4 minutes on
two cores); the suite scores a small piped capture with the same code (tests/test_bench_fidelity.py)."""
from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from odsplat.app.cli import main
from odsplat.app.pipeline import run_stage
from odsplat.reconstruction import PoseResult
from odsplat.spine.store import Capture
from odsplat.sync import load_sync


def test_a_small_27_view_capture_is_synced_and_posed_whole_with_the_defaults(tmp_path):
    out = tmp_path / "small"
    r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", "--size", "256x256",
                                  "--floor-tag-m", "0.12", "--bit-depth", "12", "--texture", "value_noise",
                                  "--frames", "12", "--pretrigger-frames", "4"])
    assert r.exit_code == 0, r.output
    cap = Capture.open(out)
    with cap.open_take(cap.manifest.takes[0].name) as t:
        assert t.frames.dtype == np.uint16 and t.bit_depth == 12 and int(t.read_frames(0, 4).max()) <= 4095
    for stage in ("qc", "sync", "poses"):                                  # magnify is not needed here
        run_stage(cap, stage)
    sync = load_sync(cap)
    assert len(sync.takes) == 27 and len(sync.ok) == 27                     # every take timed
    poses = PoseResult.read(cap)
    posed = {v.name for v in poses.views if v.kind == "take"}
    assert len(posed) >= 25, poses.report_lines()
    # Against the rig's true cameras: within a degree and 1.5 % of the distance.
    for v in poses.views:
        if v.kind != "take":
            continue
        truth = np.load(cap.root / "takes" / f"{v.name}.truth.npz")
        R_true, t_true = truth["camera_R"], truth["camera_t"]
        c, c_true = -v.R.T @ v.t, -R_true.T @ t_true
        angle = np.degrees(np.arccos(np.clip((np.trace(v.R @ R_true.T) - 1) / 2, -1, 1)))
        assert angle < 1.0 and np.linalg.norm(c - c_true) < 0.015 * np.linalg.norm(c_true - [0.2, 0, 0.3]), v.name


def test_a_capture_filmed_at_another_frame_rate_says_so_and_syncs(tmp_path):
    """`--fps` below the camera's own rate: the capture's record says the rate its takes were filmed at, so sync
    takes every one (it refused them all as filmed at 1000 fps by a 2000 fps camera, issue 43)."""
    out = tmp_path / "slow"
    r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", "--views", "2",
                                  "--fps", "1000", "--frames", "16", "--pretrigger-frames", "4"])
    assert r.exit_code == 0, r.output
    cap = Capture.open(out)
    assert cap.manifest.camera.fps == 1000.0
    run_stage(cap, "qc")
    run_stage(cap, "sync")
    sync = load_sync(cap)
    assert len(sync.ok) == 2 and len(sync.takes) == 2
