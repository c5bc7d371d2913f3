"""Beyond our own rig's defaults (issue 30): a 27-view capture at 256x256 px with 12-bit frames in 16-bit words,
a procedural texture and floor tags 15-19 px wide is synced and posed whole with the defaults."""
from __future__ import annotations

import numpy as np
from click.testing import CliRunner

from odsplat.analysis import read_analysis
from odsplat.app.cli import main
from odsplat.app.pipeline import run_stage
from odsplat.hil_sim.structure import make_structure
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


def test_a_plate_the_defaults_were_not_tuned_to_reads_its_modes_right_or_does_not_call_them_met(tmp_path,
                                                                                               bench_script):
    """Issue 43's small version: hil_sim's plate (not the arm the defaults were tuned on), 8 views at 320x240,
    1000 fps, 8-bit, value-noise paint, hit at 600 N; `odsplat capture` and `odsplat run` with the defaults, scored
    by bench/fidelity.py against the plate's analytic modes over every surface point. Every mode the analysis
    judges is right (full-field MAC >= 0.95, scale within 10 %, the video alone finds it within 1 %); the lowest is
    right whether judged or not (measured 0.976-0.979, scale 0.983-0.987; on one capture the full-field floor
    allowed it only 0.89 and flagged it: the floor errs on the safe side, and how far depends on the rest fit,
    docs/fidelity.md). The (2,1) and (1,2) modes stand near the full-field floor (0.974
    and 0.955 allowed in a run from the shell, where they read 0.957 and 0.976): judged right in some runs of the
    suite, flagged in others: the captures' DAQ records differ (real time through the sim's links; sync 0.27 us
    apart) and the rest fit amplifies that (docs/fidelity.md). The (3,1) and (3,2) modes stand above the floor at
    the sensors but not over the plate (the noise allows them 0.88 and 0.81 there; they read 0.93 and 0.84 when judged):
    below the floor, never judged (docs/fidelity.md, "The floor over the full structure")."""
    fid = bench_script("fidelity")
    out = tmp_path / "plate"
    case = fid.Case("plate_small", "plate", texture="value_noise", fps=1000.0, bit_depth=8, views=8,
                    hammer_force_n=600.0)
    r = CliRunner().invoke(main, ["capture", str(out), "--sim", "--auto", "--no-window", *case.capture_args()])
    assert r.exit_code in (0, 1), r.output              # 1: a view whose takes QC refused (the plate hides tags)
    r = CliRunner().invoke(main, ["run", str(out)])
    assert r.exit_code == 0, r.output
    cap = Capture.open(out)
    scores = fid.score_modes(cap, make_structure("plate"))
    modes = {m["mode"]: m for m in scores["modes"]}
    m = modes[1]     # right over the whole plate, judged or not (the floor's estimate errs on the safe side)
    assert m["fitted"] and m["found_within_1pct"], m
    assert m["mac_full"] >= fid.MIN_MAC and abs(m["scale"] - 1) <= fid.MAX_SCALE_ERR, m
    assert modes[4]["below_floor"] and modes[6]["below_floor"], (modes[4], modes[6])
    for m in scores["modes"]:
        if m.get("fitted") and not m["below_floor"]:
            assert m["mac_full"] >= fid.MIN_MAC and abs(m["scale"] - 1) <= fid.MAX_SCALE_ERR, m
    assert fid.targets([{"case": case.name, **scores}], None)["below_floor_never_met"]
    # with the defaults, several views' 2D tracks are triangulated against the Gaussians (analysis/triangulate.py)
    tri = read_analysis(cap).video.triangulation
    assert tri is not None and tri["n_points"] >= 3 and tri["n_views"] >= 3, tri
    assert np.isfinite(tri["expected_correlation"]) and -1 <= tri["correlation"] <= 1, tri
