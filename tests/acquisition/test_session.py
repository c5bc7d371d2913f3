"""The guided capture session on the simulated rig: 27 accepted views, every injected fault redone, SIGKILL + resume."""
from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from odsplat.acquisition.lab import load_lab_config
from odsplat.acquisition.live import PlotFeedback
from odsplat.acquisition.plan import PlanSettings, plan_views
from odsplat.acquisition.qc import HitQC
from odsplat.acquisition.session import TakeOutcome
from odsplat.acquisition.trigger import TriggeredRecord
from odsplat.hil_sim.rig import TakeTruth, truth_path
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.spine.tags import detect_tags

REPO = Path(__file__).resolve().parents[2]
SMALL = ["--frames", "16", "--pretrigger-frames", "4", "--record-s", "0.3", "--size", "400x300"]
FAULTS = {1: "double_hit", 4: "overload", 7: "dropped_packet", 10: "disconnect", 13: "dropped_frames"}
EXPECTED_FLAG = {"double_hit": "double_hit", "overload": "accel_overload", "dropped_packet": "dropped_samples",
                 "disconnect": "daq_error", "dropped_frames": "dropped_frames"}


def _capture_cmd(out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "odsplat", "capture", str(out), "--sim", "--auto", "--no-window", *SMALL, *extra]


def _env() -> dict[str, str]:
    return {**os.environ, "QT_QPA_PLATFORM": "offscreen", "PYTHONUNBUFFERED": "1"}


@pytest.mark.timeout(300)
def test_sim_manual_hammer_records_27_accepted_views_and_redoes_every_fault(tmp_path):
    out = tmp_path / "cap"
    spec = ",".join(f"{k}:{v}" for k, v in FAULTS.items())
    cmd = _capture_cmd(out, "--hammer", "manual", "--sim-faults", spec, "--hit-timeout", "10")
    run = subprocess.run(cmd, capture_output=True, text=True, env=_env(), cwd=REPO, timeout=280)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "27/27 views accepted" in run.stdout
    cap = Capture.open(out)
    takes = cap.manifest.takes
    accepted = [t for t in takes if t.qc == "accepted"]
    assert sorted(t.view for t in accepted) == list(range(27))
    # The n-th take of the run carried the n-th fault: it was rejected for it, kept, and its view redone.
    order = sorted(takes, key=lambda t: t.created_utc)
    assert len(order) == 27 + len(FAULTS)
    for k, fault in FAULTS.items():
        take = order[k]
        assert take.qc == "rejected", (k, fault, take)
        with cap.open_take(take.name) as r:
            assert EXPECTED_FLAG[fault] in r.qc.flags, (fault, r.qc)
            assert r.n_frames > 0  # the camera's frames of a rejected take are kept too
        redo = order[k + 1]
        assert redo.view == take.view and redo.qc == "accepted"
    assert "disconnected after sample" in run.stderr
    # Every take is on the rig's time base and its truth file says where the hit really was.
    take = accepted[0]
    with cap.open_take(take.name) as r:
        truth = TakeTruth.load(truth_path(cap.root / take.file))
        force = r.channel("force")
        trig = r.trigger
        t0_sample = round(r.daq_t0_s * r.sample_rate_hz)
        np.testing.assert_allclose(force, truth.force_n[t0_sample:t0_sample + len(force)], atol=0.1)
        assert trig.trigger_time_s * truth.daq_true_rate_hz == pytest.approx(
            np.ceil(truth.impact_time_s[0] * truth.daq_true_rate_hz +
                    truth.daq_true_rate_hz * 1e-3 / np.pi * np.arcsin(10 / truth.impact_peak_n[0])), abs=1)
        assert r.frame_counter[trig.camera_trigger_frame] == 0 and r.n_frames == 16
        assert np.array_equal(r.frame_counter, truth.frame_counter)
        assert abs(r.attrs["pose_angular_error_deg"]) < 6.0  # the engineer put it ~2 deg off; the tags saw it


def _accepted_hashes(out: Path) -> dict[str, str]:
    manifest = json.loads((out / "capture.json").read_text())
    return {t["name"]: hashlib.sha256((out / t["file"]).read_bytes()).hexdigest()
            for t in manifest["takes"] if t["qc"] == "accepted"}


@pytest.mark.timeout(300)
def test_sigkill_mid_session_then_resume_loses_nothing(tmp_path):
    out = tmp_path / "cap"
    proc = subprocess.Popen(_capture_cmd(out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=_env(),
                            cwd=REPO)
    deadline = time.monotonic() + 200
    try:
        while time.monotonic() < deadline:
            if (out / "capture.json").exists() and len(_accepted_hashes(out)) >= 8:
                break
            time.sleep(0.05)
        else:
            pytest.fail("the session did not get to 8 takes")
        time.sleep(0.2)  # most likely mid-take: a frame or two into the next take file
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
    before = _accepted_hashes(out)
    assert len(before) >= 8
    run = subprocess.run(_capture_cmd(out), capture_output=True, text=True, env=_env(), cwd=REPO, timeout=280)
    assert run.returncode == 0, run.stderr[-3000:]
    after = _accepted_hashes(out)
    assert {k: after[k] for k in before} == before  # accepted takes untouched
    cap = Capture.open(out)
    accepted = [t for t in cap.manifest.takes if t.qc == "accepted"]
    assert sorted(t.view for t in accepted) == list(range(27))
    assert cap.partial_takes() == [] and cap.unlisted_takes() == []
    # A take cut by the kill is kept, recovered and marked, never counted as good.
    for t in cap.manifest.takes:
        if t.status == "recovered":
            assert t.qc != "accepted"


def test_resume_with_another_plan_is_refused_and_static_photos(tmp_path):
    out = tmp_path / "cap"
    run = subprocess.run(_capture_cmd(out, "--views", "2", "--static-photos"), capture_output=True, text=True,
                         env=_env(), cwd=REPO, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    photos = sorted(p.name for p in (out / "static").iterdir())
    assert photos == ["view_00.png", "view_01.png"]
    still = cv2.imread(str(out / "static" / "view_00.png"), cv2.IMREAD_UNCHANGED)
    assert still.dtype == np.uint16 and still.shape == (300, 400)
    assert len(detect_tags(still)) >= 2  # usable for poses: the floor tags are sharp in it
    again = subprocess.run(_capture_cmd(out, "--views", "3"), capture_output=True, text=True, env=_env(), cwd=REPO,
                           timeout=120)
    assert again.returncode == 2 and "views differ from this session's plan" in again.stderr


def test_cli_refuses_inconsistent_modes(tmp_path):
    run = subprocess.run([sys.executable, "-m", "odsplat", "capture", str(tmp_path / "c"), "--auto"],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2 and "give exactly one of --sim or --config" in run.stderr


def test_live_window_draws_the_last_hit_and_coverage(monkeypatch):
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    plan = plan_views(PlanSettings(n_views=5))
    lines: list[str] = []
    fb = PlotFeedback(lines.append, plan)
    fs = 1000.0
    t = np.arange(200)
    data = np.vstack([np.where((t > 50) & (t < 53), 150.0, 0.0), np.sin(t / 5.0)])
    record = TriggeredRecord(51, 0, 200, fs, ("force", "acc1"), data)
    qc = HitQC((), (), 150.0, (0.0,), {"acc1": 1.0})
    fb.show_view(plan[2], 5, "view 3/5")
    fb.show_take(TakeOutcome("v02_000", 2, True, qc, None), record, 0.3, "")
    items = fb.force_plot.listDataItems()
    assert len(items) == 1 and np.nanmax(items[0].getData()[1]) == 150.0
    assert len(fb.accel_plot.listDataItems()) == 1
    assert fb._done.data.size == 1 and "coverage 30%" in lines[-1]
    fb.close()


def test_lab_config_parses_and_names_bad_fields(tmp_path):
    good = tmp_path / "lab.toml"
    good.write_text('''
[daq]
url = "simdaq://rig"
sample_rate_hz = 25600
channels = [ { name = "force", input = 0, kind = "force", sensitivity_v_per_unit = 0.00225 } ]
[camera]
driver = "opencv"
source = "take.avi"
intrinsics = { fx_px = 500.0, fy_px = 500.0, cx_px = 159.5, cy_px = 119.5 }
''')
    lab = load_lab_config(good)
    assert lab.channels[0].full_scale == pytest.approx(10 / 0.00225) and lab.camera.intrinsics.fx_px == 500.0
    bad = tmp_path / "bad.toml"
    bad.write_text(good.read_text().replace('kind = "force"', 'kind = "forse"'))
    with pytest.raises(InputError, match="'force'.kind: expected one of"):
        load_lab_config(bad)
    bad.write_text(good.read_text().replace("sample_rate_hz = 25600", 'sample_rate_hz = "fast"'))
    with pytest.raises(InputError, match=r"bad.toml: daq.sample_rate_hz: expected a number"):
        load_lab_config(bad)
    with pytest.raises(InputError, match="missing section \\[camera\\]"):
        bad.write_text("[daq]\nurl='x'\n")
        load_lab_config(bad)


def test_camera_that_never_triggers_is_flagged_and_the_daq_record_still_checked(tmp_path):
    """The trigger box is set above the hit: the DAQ triggers, the camera times out. The take keeps the DAQ
    record, runs the usual QC on it and is rejected for the camera alone."""
    from odsplat.acquisition.plan import PlanSettings
    from odsplat.acquisition.session import CaptureSession, SessionSettings
    from odsplat.acquisition.trigger import HammerTrigger
    from odsplat.hil_sim.bench import SimBench
    from odsplat.hil_sim.rig import RigConfig, SimRig

    bench = SimBench(SimRig(config=RigConfig(trigger_level_n=1e6)))
    settings = SessionSettings(name="cap", plan=PlanSettings(n_views=1), n_frames=16, pretrigger_frames=4,
                               trigger=HammerTrigger(pretrigger_s=0.02, record_s=0.2), max_attempts=1,
                               camera_timeout_s=0.3)
    report = CaptureSession(tmp_path / "cap", settings, bench).run()
    (outcome,) = report.outcomes
    assert not outcome.accepted and outcome.qc is not None
    assert outcome.qc.reasons == ("camera_timeout",)  # and nothing else: the DAQ record passed every check
    assert outcome.qc.peak_force_n > 100
    cap = Capture.open(tmp_path / "cap")
    with cap.open_take(outcome.name) as r:
        assert r.qc.flags == ("camera_timeout",) and r.n_frames == 0
        assert r.trigger.trigger_sample is not None and r.n_samples > 0
