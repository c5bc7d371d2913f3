"""`odsplat batch` on a small campaign: two simulated captures on a local Dask cluster of two worker processes,
one of them broken so that magnify's per-view tasks fail; the failure is reported with its capture, stage and
one line while the others finish; after the fix a rerun does only what failed; the results equal `odsplat run`'s."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py
import hdf5plugin  # noqa: F401  (the frame files' compression filter)
import numpy as np
import pytest

from odsplat.acquisition import CaptureSession, HammerTrigger, PlanSettings, SessionSettings
from odsplat.app.config import STAGES
from odsplat.hil_sim import SimBench, SimBenchSettings
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake

N_VIEWS = 3
# Test-sized: 40 px Gaussians, 12 timesteps, few iterations, a low LSCF order for 24-frame takes (the test compares
# two runs' results, not their accuracy: tests/test_pipeline.py and the fidelity tests judge those), no mp4s.
CONFIG = """
[magnify]
every_view = true    # the default magnifies one view to watch; every view exercises magnify's per-view tasks
video = false
[reconstruct]
width_px = 40
n_timesteps = 12
[reconstruct.fit]
iters_t0 = 80
[analyze]
max_order = 30
image_poles = false
crosscheck_views = 0
triangulate_views = 0
plots = false
[report]
mode_clips = false
"""
# Above the 2000 fps camera's Nyquist: every view's magnifier refuses it, inside magnify's per-view tasks.
BROKEN = CONFIG.replace("[magnify]\n", "[magnify]\nband_hz = [20, 1500]\n")
# a run's ids and times, and its pools' widths (a run on its own cores fits them to the memory budget; a batch
# hands the per-view work to its cluster)
VOLATILE = {"created_utc", "generation", "run_id", "fingerprint", "seconds", "workers"}


def _odsplat(*args, code: int = 0) -> tuple[str, float]:
    started = time.perf_counter()
    r = subprocess.run([sys.executable, "-m", "odsplat", *map(str, args)], capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == code, r.stdout + r.stderr
    return r.stdout, time.perf_counter() - started


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """Two captures of three views and 24 frames (a few seconds each), with the test-sized configuration."""
    root = tmp_path_factory.mktemp("campaign")
    for seed in (1, 2):
        out = root / f"cap{seed}"
        session = SessionSettings(name=out.name, plan=PlanSettings(n_views=N_VIEWS), n_frames=24, pretrigger_frames=4,
                                  trigger=HammerTrigger(pretrigger_s=0.01, record_s=0.05), static_photos=True)
        assert CaptureSession(out, session, SimBench(settings=SimBenchSettings(seed=seed))).run().complete
        (out / "odsplat.toml").write_text(CONFIG)
    return root


def _stripped(doc):
    if isinstance(doc, dict):
        return {k: _stripped(v) for k, v in doc.items() if k not in VOLATILE}
    if isinstance(doc, list):
        return [_stripped(v) for v in doc]
    return doc


def _frames(cap: Capture, path: Path) -> tuple[np.ndarray, np.ndarray]:
    if path.parent == cap.paths.aligned_dir:       # computed from the raw take as it is read
        with AlignedTake(cap, path) as f:
            return f.read_frames(), f.times_s
    with h5py.File(path, "r") as f:
        return f["frames"][()], f["times_s"][()]


def _assert_same_results(a: Capture, b: Capture, exact_magnified: bool) -> None:
    """sync.json's numbers, every aligned and magnified frame file's frames and times, analysis.json's modes."""
    assert _stripped(json.loads(a.paths.sync_json.read_text())) == _stripped(json.loads(b.paths.sync_json.read_text()))
    files = sorted(a.paths.aligned_dir.glob("*.h5")) + sorted(a.paths.magnified_dir("phase").glob("*.h5"))
    assert len(files) == 2 * N_VIEWS
    for path in files:
        other = b.paths.root / path.relative_to(a.paths.root)
        (x, tx), (y, ty) = _frames(a, path), _frames(b, other)
        assert np.array_equal(tx, ty), path
        if exact_magnified or "magnified" not in path.parts:
            assert np.array_equal(x, y), path
        else:   # torch on several threads per view: the last stored quarter DN may differ (see magnify_capture)
            assert np.abs(x.astype(int) - y.astype(int)).max() <= 1, path
    modes = [json.loads(c.paths.analysis_json.read_text())["modes"] for c in (a, b)]
    assert modes[0] and _stripped(modes[0]) == _stripped(modes[1])


def _ran(output: str, capture: str) -> set[str]:
    """The stages a capture's line in the batch's summary says it ran."""
    line = next(line for line in output.splitlines() if re.match(rf".*/{capture}: ok in", line))
    m = re.search(r"\(ran (.*)\)", line)
    return set(m.group(1).split(", ")) if m else set()


def test_batch_reports_a_failure_finishes_the_rest_reruns_only_what_failed_and_equals_a_serial_run(campaign,
                                                                                                   tmp_path):
    batch, serial = tmp_path / "batch", tmp_path / "serial"
    shutil.copytree(campaign, batch)
    shutil.copytree(campaign, serial)
    (batch / "cap2" / "odsplat.toml").write_text(BROKEN)
    caps = [batch / f"cap{i}" for i in (1, 2)]

    out, batch_s = _odsplat("batch", *caps, "--workers", 2, code=1)
    assert re.search(r"^dashboard: http://\S+", out, re.M), out
    for stage in STAGES:    # a line per capture and stage as they finish
        assert f"cap1: [{stage}] done in" in out, out
    failed = sorted({line for line in out.splitlines() if "FAILED" in line})   # as it finished, and in the summary
    assert len(failed) == 1 and failed[0].startswith(f"{caps[1]}: FAILED in magnify: "), out
    assert failed[0].endswith("--band: expected 0 < low < high < fps/2 = 1000 Hz; got 20 to 1500 Hz"), failed
    assert "1 of 2 capture(s) ok, 1 failed" in out
    assert all(Capture.open(caps[0]).paths.stamp(s).is_file() for s in STAGES)
    broken = Capture.open(caps[1])
    assert broken.paths.stamp("qc").is_file() and broken.paths.stamp("sync").is_file()
    assert not broken.paths.stamp("magnify").exists()
    assert not list(broken.paths.magnified_dir("phase").glob("*.h5"))    # the failed stage left no files

    (caps[1] / "odsplat.toml").write_text(CONFIG)
    out, rerun_s = _odsplat("batch", *caps, "--workers", 2)
    assert "2 of 2 capture(s) ok, 0 failed" in out, out
    assert _ran(out, "cap1") == set(), out
    assert _ran(out, "cap2") == {"magnify", "poses", "reconstruct", "analyze", "report"}, out

    # `odsplat run` on a copy of the capture the batch finished in two goes: the same numbers, frames and modes.
    # The batch magnifies with one thread per view, as `odsplat run` does when the views are at least as many as
    # the cores.
    exact = (os.cpu_count() or 1) <= N_VIEWS
    for i in (2,):
        seconds = _odsplat("run", serial / f"cap{i}")[1]
        _assert_same_results(Capture.open(batch / f"cap{i}"), Capture.open(serial / f"cap{i}"), exact)
        print(f"cap{i}: odsplat run {seconds:.1f} s")
    print(f"batch of 2 (cap2 failing in magnify) {batch_s:.1f} s, rerun {rerun_s:.1f} s")
