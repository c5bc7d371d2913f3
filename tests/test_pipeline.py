"""The pipeline on a small simulated capture: `odsplat run` from raw takes to the report, the skip rule, reruns of
what is stale, kill safety, the derived files' self-description, the configuration and notebook use."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import odsplat
from odsplat.app.cli import main
from odsplat.app.config import STAGES, load_config
from odsplat.app.pipeline import is_current, status
from odsplat.processing import MagnifiedVideo, MagnifyResult
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, SyncSettings, load_sync

from .conftest import RUN_OUTPUT, SMALL_PIPELINE_CONFIG, piped_copy

CONFIG = SMALL_PIPELINE_CONFIG
N_VIEWS = 8
RIG_MODES_HZ = (23.5, 31.0, 86.0, 142.0, 262.0, 371.0)


def _cli(args, code=0):
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert r.exit_code == code, r.output + repr(r.exception)
    return r.output


def _statuses(output: str) -> dict[str, str]:
    """stage -> ran/current from the summary table `odsplat run` prints last."""
    out = {}
    for line in output.splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[0] in STAGES and parts[1] in ("ran", "current"):
            out[parts[0]] = parts[1]
    return out


@pytest.fixture(scope="module")
def piped(piped_original, tmp_path_factory):
    """Eight views of 24 frames with static photos, through `odsplat run` once (the session's piped capture,
    copied), and what the run printed."""
    cap = piped_copy(piped_original, tmp_path_factory.mktemp("pipeline") / "cap")
    return Capture.open(cap), (cap.parent / RUN_OUTPUT).read_text().replace(str(piped_original), str(cap))


def _copy(piped, tmp_path) -> Capture:
    cap, _ = piped
    shutil.copytree(cap.root, tmp_path / "cap")
    return Capture.open(tmp_path / "cap")


def test_run_goes_from_raw_takes_to_the_report(piped):
    cap, text = piped
    assert _statuses(text) == {s: "ran" for s in STAGES}
    assert f"report: {cap.paths.report_html}" in text
    html = cap.paths.report_html.read_text()
    assert "<html" in html and "modes" in html.lower()
    for stage in STAGES:
        assert cap.paths.stamp(stage).is_file()
    # The stages' results, against the rig: every take synced, every view posed, the first bending modes found.
    assert len(load_sync(cap).ok) == N_VIEWS
    poses = json.loads(cap.paths.poses_json.read_text())
    assert len([v for v in poses["views"] if v["kind"] == "take"]) == N_VIEWS
    doc = json.loads(cap.paths.analysis_json.read_text())
    found = np.array([m["freq_hz"] for m in doc["modes"]])
    assert any(np.min(np.abs(found - f)) < 0.05 * f for f in RIG_MODES_HZ), found
    # Every derived index file describes itself one way: kind, schema, this capture, the settings it was made with.
    for path in (cap.paths.qc_json, cap.paths.sync_json, cap.paths.magnify_json("phase"), cap.paths.poses_json,
                 cap.paths.reconstruction_json, cap.paths.analysis_json):
        d = json.loads(path.read_text())
        assert d["kind"].startswith("odsplat.") and isinstance(d["schema_version"], int), path
        assert d["capture_id"] == cap.id and "settings" in d["provenance"], path
    assert json.loads(cap.paths.reconstruction_json.read_text())["provenance"]["settings"]["width_px"] == 64
    # Each stage's result reads back through its owner's contract.
    assert odsplat.reconstruction.ReconstructResult.read(cap).n_views == N_VIEWS
    assert odsplat.reconstruction.PoseResult.read(cap).method in ("sfm", "tags")
    assert odsplat.processing.MagnifyResult.read(cap, "phase").alpha == 20.0
    assert odsplat.acquisition.QCReport.read(cap).takes[0].status == "accepted"
    assert odsplat.analysis.read_analysis(cap).to_json()["modes"] == doc["modes"]


def test_a_second_run_skips_every_stage(piped):
    cap, _ = piped
    files = lambda: {p: p.stat().st_mtime_ns for p in cap.paths.root.rglob("*")  # noqa: E731
                     if p.is_file() and p != cap.paths.lock}
    before = files()
    text = _cli(["run", cap.root])
    assert files() == before        # skipped, not redone: no derived file written, none removed (how fast: not timed)
    assert _statuses(text) == {s: "current" for s in STAGES}
    assert all(current for _, current, _ in status(cap))


def test_changed_settings_rerun_that_stage_and_what_depends_on_it(piped, tmp_path):
    cap = _copy(piped, tmp_path)
    before = load_sync(cap).created_utc
    (cap.root / "odsplat.toml").write_text(CONFIG.replace("[magnify]\n", "[magnify]\nalpha = 35\n"))
    text = _cli(["run", cap.root])
    # The default reconstruction reads the raw frames: nothing downstream depends on the magnified ones.
    assert _statuses(text) == {**{s: "current" for s in STAGES}, "magnify": "ran"}
    assert "settings changed (alpha)" in text
    assert load_sync(cap).created_utc == before
    assert json.loads(cap.paths.magnify_json("phase").read_text())["alpha"] == 35.0
    # The paper's order reconstructs from the magnified frames: there the magnification reaches the model.
    assert is_current(cap, "magnify", load_config(cap, sets=("magnify.alpha=20",)))[0] is False
    # It needs every view magnified, where the default magnifies the first only to watch: magnify reruns too
    config = load_config(cap, sets=("reconstruct.motion='timestep'",))
    assert config.magnify.every_view and is_current(cap, "magnify", config) == (False, "settings changed (every_view)")
    current, why = is_current(cap, "reconstruct", config)
    assert not current and "settings changed" in why and "motion" in why and "source" in why
    # A rerun upstream makes everything downstream stale, even with the same settings.
    _cli(["sync", cap.root, "--no-image-check", "--no-plot"])
    stale = {name: why for name, current, why in status(cap) if not current}
    assert set(stale) == {"sync", "magnify", "reconstruct", "analyze", "report"}, stale
    assert stale["sync"] == "settings changed (check_with_image, plot)"   # those options were for that run alone
    assert stale["magnify"] == "inputs changed (sync)" and stale["reconstruct"] == "inputs changed (sync)"
    assert stale["report"] == "analyze will run first"


def test_sigkill_during_a_stage_then_run_gives_a_complete_correct_result(piped, tmp_path):
    cap = _copy(piped, tmp_path)
    sync_before = load_sync(cap)
    frames_before = {t.name: AlignedTake(cap, cap.paths.aligned(t.name)).read_frames() for t in sync_before.ok[:3]}
    stamp = cap.paths.stamp("sync")
    for _ in range(3):      # sync writes its files within a few hundred ms: a try that misses them tries again
        if _kill_once_sync_writes(cap, stamp):
            break
    else:
        pytest.fail("sync finished three times before it could be killed while writing")
    assert _processes_on(cap.root, within_s=30) == [], "a killed run's pool workers outlived it"
    assert not stamp.exists()
    assert dict((n, c) for n, c, _ in status(cap))["sync"] is False
    text = _cli(["run", cap.root])
    statuses = _statuses(text)
    assert statuses["qc"] == "current" and statuses["poses"] == "current"
    assert all(statuses[s] == "ran" for s in ("sync", "magnify", "reconstruct", "analyze", "report"))
    after = load_sync(cap)
    assert [t.name for t in after.ok] == [t.name for t in sync_before.ok]
    np.testing.assert_allclose([t.offset_s for t in after.ok], [t.offset_s for t in sync_before.ok], atol=1e-9)
    for name, frames in frames_before.items():
        np.testing.assert_array_equal(AlignedTake(cap, cap.paths.aligned(name)).read_frames(), frames)
    assert all(current for _, current, _ in status(cap))


def _kill_once_sync_writes(cap: Capture, stamp: Path) -> bool:
    """Run `odsplat run --force sync` and SIGKILL it as soon as sync has rewritten one of its files (the stage has
    begun, its stamp is gone, and its results are half old, half new); False if the stage ended first."""
    started_ns = time.time_ns()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "odsplat", "run", str(cap.root), "--force", "sync"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    folder, deadline, begun = cap.paths.aligned_dir, time.monotonic() + 120, False
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            begun = begun or not stamp.exists()
            if begun and stamp.exists():
                return False                                   # the stage ended between two looks
            if begun and any(f.stat().st_mtime_ns > started_ns for f in folder.glob("*.h5")):
                return True
            time.sleep(0.002)
        return False
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()


def _processes_on(path: Path, within_s: float) -> list[str]:
    """The command lines of the processes still running on `path` once they have had `within_s` to end."""
    deadline = time.monotonic() + within_s
    while True:
        found = []
        for proc in Path("/proc").glob("[0-9]*"):
            try:
                cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:     # ended meanwhile
                continue
            if str(path) in cmd:
                found.append(cmd)
        if not found or time.monotonic() > deadline:
            return found
        time.sleep(0.2)


def _assert_index_lists_its_own_run(cap: Capture, stage: str) -> None:
    """The stage's index reads, and every file it lists is there and of the run it names."""
    if stage == "sync":
        index = load_sync(cap)
        for t in index.ok:
            with AlignedTake(cap, cap.paths.aligned(t.name), index.generation) as f:
                assert f.n_frames > 0
    else:
        index = MagnifyResult.read(cap, "phase")
        for t in index.takes:
            with MagnifiedVideo(cap.paths.root / t.file, index.generation) as f:
                assert f.n_frames == t.n_frames


def _derived_files(cap: Capture) -> list[str]:
    return sorted(str(p.relative_to(cap.paths.root)) for p in cap.paths.root.rglob("*") if p.is_file())


def test_sync_and_magnify_killed_at_random_points_then_rerun_leave_one_consistent_set(piped, tmp_path):
    """A stage's frame files and their index are committed together: killed anywhere (seeded points in each
    stage's run), the index is gone or lists only files of its own run, and the rerun gives the same result as
    an uninterrupted run with no temporaries left."""
    cap = _copy(piped, tmp_path)
    before = {t.name: AlignedTake(cap, cap.paths.aligned(t.name)).read_frames() for t in load_sync(cap).ok[:2]}
    files_before = _derived_files(cap)
    rng = np.random.default_rng(29)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    for stage, index in (("sync", cap.paths.sync_json), ("magnify", cap.paths.magnify_json("phase"))):
        for _ in range(1):      # one seeded point per stage (the test above kills sync within `odsplat run` too)
            proc = subprocess.Popen([sys.executable, "-m", "odsplat", stage, str(cap.root)], env=env,
                                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            deadline = time.monotonic() + 60
            while index.exists() and time.monotonic() < deadline:     # the run has begun once its index is gone
                time.sleep(0.02)
            time.sleep(float(rng.uniform(0.0, 2.5)))
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            assert _processes_on(cap.root, within_s=30) == [], f"a killed {stage}'s pool workers outlived it"
            if proc.returncode == 0:
                continue                                                # finished first: nothing to check
            if index.exists():     # killed after its index was committed (a short run can be): its own files only
                _assert_index_lists_its_own_run(cap, stage)
                continue
            with pytest.raises(InputError, match="no sync result|no phase magnification"):
                load_sync(cap) if stage == "sync" else MagnifyResult.read(cap, "phase")
    # The stages after magnify are stale but unchanged on disk; the test above reruns them after a kill.
    text = _cli(["run", cap.root, "--to", "magnify"])
    assert _statuses(text) == {"qc": "current", "sync": "ran", "magnify": "ran"}, text
    assert not [p for p in cap.paths.root.rglob("*.tmp")]
    assert _derived_files(cap) == files_before
    for name, frames in before.items():
        np.testing.assert_array_equal(AlignedTake(cap, cap.paths.aligned(name)).read_frames(), frames)


def test_a_frame_file_of_another_run_is_refused(piped, tmp_path):
    """An aligned file that its index does not vouch for (left by an interrupted run) stops the reader."""
    import h5py

    cap = _copy(piped, tmp_path)
    name = load_sync(cap).ok[0].name
    with h5py.File(cap.paths.aligned(name), "r+") as f:
        f.attrs["generation"] = "0123456789abcdef"
    out = _cli(["magnify", cap.root], code=2)
    errors = [line for line in out.splitlines() if "odsplat: error:" in line]
    assert len(errors) == 1 and f"{name}.h5: written by another run of its stage" in errors[0]
    assert "Traceback" not in out
    assert not cap.paths.magnify_json("phase").exists()          # that run wrote no index
    assert not list(cap.paths.magnified_dir("phase").glob("*.h5"))  # ... and left no files of its own


def test_foreign_and_newer_derived_files_are_refused_with_one_line(piped, tmp_path):
    cap = _copy(piped, tmp_path)
    doc = json.loads(cap.paths.sync_json.read_text())
    cap.paths.sync_json.write_text(json.dumps({**doc, "capture_id": "someone-elses"}))
    out = _cli(["magnify", cap.root], code=2)
    assert out.count("\n") == 1 and "sync.json" in out and "belongs to another capture" in out
    cap.paths.sync_json.write_text(json.dumps({**doc, "schema_version": 99}))
    out = _cli(["magnify", cap.root], code=2)
    assert out.count("\n") == 1 and "schema 99 is newer" in out
    cap.paths.sync_json.write_text(json.dumps({**doc, "kind": "odsplat.poses"}))
    with pytest.raises(InputError, match="not an odsplat.sync file"):
        load_sync(cap)
    # A stage stamp from another capture stops the pipeline too, with one line naming it.
    stamp = json.loads(cap.paths.stamp("qc").read_text())
    cap.paths.stamp("qc").write_text(json.dumps({**stamp, "capture_id": "someone-elses"}))
    out = _cli(["run", cap.root], code=2)
    assert out.strip().splitlines()[-1].startswith("odsplat: error:") and "qc.json" in out


def test_config_prints_the_effective_settings_and_names_bad_ones(piped, tmp_path):
    cap, _ = piped
    text = _cli(["config", cap.root, "--set", "analyze.fmax_hz=900"])
    table = tomllib.loads(text)
    assert table["reconstruct"]["width_px"] == 64 and table["reconstruct"]["fit"]["iters_t0"] == 150
    assert table["analyze"]["fmax_hz"] == 900.0 and table["magnify"]["alpha"] == 20.0
    assert "odsplat.toml" in text.splitlines()[0]
    # The printed file is a configuration: read back, it gives the same settings.
    path = tmp_path / "odsplat.toml"
    path.write_text(text)
    again = load_config(path=path)
    assert again.to_dict() == load_config(cap, sets=("analyze.fmax_hz=900",)).to_dict()
    out = _cli(["config", cap.root, "--set", "magnify.alhpa=3"], code=2)
    assert out.count("\n") == 1 and "alhpa" in out
    out = _cli(["run", cap.root, "--set", "magnify.alpha=-1"], code=2)
    assert out.count("\n") == 1 and "alpha" in out
    path.write_text("[magnify]\nalpha = 'big'\n")
    out = _cli(["run", cap.root, "--config", path], code=2)
    assert out.count("\n") == 1 and str(path) in out and "alpha" in out


def test_notebook_use_writes_nothing_into_the_capture(piped, tmp_path):
    cap, _ = piped
    before = {p: p.stat().st_mtime_ns for p in cap.paths.root.rglob("*") if p.is_file()}
    scratch = odsplat.Capture.open(cap.root, derived=tmp_path / "scratch")
    result = odsplat.sync.run(scratch, odsplat.SyncSettings(write_frames=False, plot=False, check_with_image=False))
    assert len(result.ok) == N_VIEWS and (tmp_path / "scratch" / "sync.json").is_file()
    done = odsplat.run(scratch, odsplat.load_config(cap), stop="qc")
    assert [s.stage for s in done.stages] == ["qc"] and scratch.paths.stamp("qc").is_file()
    after = {p: p.stat().st_mtime_ns for p in cap.paths.root.rglob("*") if p.is_file()}
    assert after == before
    assert isinstance(odsplat.SyncSettings(), SyncSettings)


def test_python_dash_m_odsplat():
    r = subprocess.run([sys.executable, "-m", "odsplat", "run", "--help"], capture_output=True, text=True)
    assert r.returncode == 0 and "--from" in r.stdout and "--force" in r.stdout


def test_config_status_says_which_stages_are_current_and_the_working_width(piped, tmp_path):
    cap = _copy(piped, tmp_path)
    text = _cli(["config", cap.root, "--status"])
    assert "[reconstruct]" in text
    for stage in STAGES:
        assert f"# {stage:<12} current:" in text or f"# {stage:<12} n/a:" in text, stage
    assert "\n# reconstruct.width_px = 64: as set (reconstruct.width_px)\n" in text     # CONFIG's
    # With the defaults, the width follows the views: the node spacing is 5 px of these 400 px views, and two working
    # pixels a node need 160 px.
    (tmp_path / "defaults.toml").write_text("")
    text = _cli(["config", cap.root, "--status", "--config", tmp_path / "defaults.toml"])
    width = next(line for line in text.splitlines() if line.startswith("# reconstruct.width_px = "))
    assert width.startswith("# reconstruct.width_px = 160: node spacing ") and "5.0 px of the 400 px" in width, width
    assert "# reconstruct  stale: settings changed (" in text
