"""Sync on a capture recorded on the simulated rig, against its ground truth."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from odsplat.hil_sim.rig import TakeTruth, truth_path
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, SyncResult, SyncSettings, load_sync, sync_capture
from odsplat.sync.image import DisplacementBasis, fit_frame_times, motion_gram, noise_sd

from .conftest import FPS, TRIGGER_DELAY_S

REPO = Path(__file__).resolve().parents[2]


def _true_offset_s(cap: Capture, name: str) -> float:
    tr = TakeTruth.load(truth_path(cap.takes_dir / f"{name}.h5"))
    # DAQ time is rig time here (no DAQ drift): the middle of counter 0's exposure after the impact onset.
    return tr.trigger_frame_time_s + 0.5 * tr.camera_exposure_s - tr.impact_time_s[0]


def _errors_frames(cap: Capture, result: SyncResult) -> dict[str, float]:
    return {t.name: (t.offset_s - _true_offset_s(cap, t.name)) * FPS for t in result.ok}


def _copy(cap: Capture, dest: Path) -> Capture:
    shutil.copytree(cap.root, dest, ignore=shutil.ignore_patterns("derived"))
    return Capture.open(dest)


@pytest.fixture(scope="module")
def ttl_result(sim_capture) -> SyncResult:
    return sync_capture(sim_capture, SyncSettings(camera_trigger_delay_s=TRIGGER_DELAY_S), progress=False)


def test_strobe_sync_is_within_two_hundredths_of_a_frame(sim_capture, ttl_result):
    res = ttl_result
    assert [t.name for t in res.takes] == [t.name for t in sim_capture.manifest.takes if t.qc == "accepted"]
    assert len(res.ok) == 4 and res.fps == FPS
    errors = _errors_frames(sim_capture, res)
    assert max(abs(e) for e in errors.values()) < 0.02, errors
    offsets = [t.offset_s * FPS for t in res.ok]
    assert np.ptp(offsets) > 0.2  # the takes really were out of step: random phases, a jittery trigger
    for t in res.ok:
        assert t.method == "ttl" and t.residual_frames < 0.03
        assert abs(t.image_check_frames) < 0.2, t  # the images agree with the strobe
        assert t.xcorr_coeff > 0.99 and abs(t.xcorr_lag_s) * 25_600 < 0.25  # responses line up once locked
        assert not {"anchor_mismatch", "image_disagrees", "onset_inconsistent"} & set(t.flags)
    doc = json.loads(sim_capture.paths.sync_json.read_text())
    assert doc["kind"] == "odsplat.sync" and doc["capture_id"] == sim_capture.id
    again = load_sync(sim_capture)
    assert [(t.name, t.offset_s, t.flags) for t in again.takes] == [(t.name, t.offset_s, t.flags) for t in res.takes]


def test_aligned_frames_are_on_the_common_grid(sim_capture, ttl_result):
    """Date each aligned take's frames again from its images: they must now sit on the grid's own times."""
    res = ttl_result
    assert res.n_frames >= 55 and res.t0_s == pytest.approx(round(res.t0_s * FPS) / FPS)
    exposure = sim_capture.manifest.camera.exposure_s
    for t in res.ok:
        with (AlignedTake(sim_capture, sim_capture.paths.root / t.aligned_file) as a,
              sim_capture.open_take(t.name) as raw):
            assert a.n_frames == res.n_frames and a.frame_shape == raw.frame_shape
            np.testing.assert_allclose(a.times_s, res.times_s)
            rest = a.times_s + 0.5 * exposure < -0.5 / FPS  # frames wholly before the impact
            frames = a.read_frames()
            mean, var = frames[rest].mean(axis=0), frames[rest].var(axis=0, ddof=1)
            motion = motion_gram(iter([frames]), len(frames), mean, noise_sd(mean, var, int(rest.sum())))
            basis = DisplacementBasis.from_take(raw, t.hit_daq_time_s, exposure)
            start = t.hit_daq_time_s + res.t0_s - 0.5 * exposure  # where grid frame 0's exposure should start
            timing = fit_frame_times(motion, np.arange(len(frames)), 1 / FPS, basis, start, rest=rest)
            assert abs((timing.frame0_start_s - start) * FPS) < 0.15, (t.name, timing)


def test_image_sync_without_the_strobe_is_within_a_tenth_of_a_frame(sim_capture):
    res = sync_capture(sim_capture, SyncSettings(method="image", write_frames=False,
                                                 camera_trigger_delay_s=TRIGGER_DELAY_S), progress=False)
    errors = _errors_frames(sim_capture, res)
    assert len(errors) == 4
    assert float(np.sqrt(np.mean(np.square(list(errors.values()))))) < 0.1, errors
    assert max(abs(e) for e in errors.values()) < 0.2, errors
    for t in res.ok:
        assert t.method == "image" and t.image_motion_z > 50 and "motion_before_hit" not in t.flags


def test_rejected_takes_are_excluded_with_their_reason_or_repaired(sim_capture):
    res = sync_capture(sim_capture, SyncSettings(takes="all", write_frames=False, check_with_image=False,
                                                 camera_trigger_delay_s=TRIGGER_DELAY_S), progress=False)
    by_name = {t.name: t for t in res.takes}
    double = by_name["v01_000"]
    assert double.status == "excluded" and double.error.startswith("force: 2 hits found")
    assert double.offset_s is None
    dropped = by_name["v02_000"]  # two frames lost: the strobe still dates every frame, the gap is filled
    assert dropped.status == "ok" and dropped.dropped_counters == [3, 4] and "dropped_frames_filled" in dropped.flags
    assert abs(_errors_frames(sim_capture, res)["v02_000"]) < 0.02


def test_aligned_takes_read_alike_in_any_chunks_and_impulse_normalisation_scales_the_motion(sim_capture, tmp_path):
    cap = _copy(sim_capture, tmp_path / "cap")
    base = SyncSettings(camera_trigger_delay_s=TRIGGER_DELAY_S, check_with_image=False)
    one = sync_capture(cap, SyncSettings(**{**base.__dict__, "workers": 2}), progress=False)   # a process pool
    t = one.ok[1]
    with AlignedTake(cap, cap.paths.root / t.aligned_file) as a:
        whole = a.read_frames()
        # read in chunks, or one frame at a time: the same frames, to the filter's rounding (a hundredth of a DN)
        np.testing.assert_allclose(np.concatenate(list(a.iter_frames(7))), whole, rtol=0, atol=0.01)
        np.testing.assert_allclose(np.stack([a.read_frames(k, k + 1)[0] for k in range(a.n_frames)]), whole,
                                   rtol=0, atol=0.01)
        np.testing.assert_array_equal(a.read_frames(), whole)       # and the same read twice: the same numbers
    # one take after another in this process: the same frames; the file is the recipe, not the frames
    serial = sync_capture(cap, SyncSettings(**{**base.__dict__, "workers": 1}), progress=False)
    path = cap.paths.root / serial.ok[1].aligned_file
    with AlignedTake(cap, path) as a:
        np.testing.assert_array_equal(a.read_frames(), whole)
    assert path.stat().st_size < 0.01 * (cap.root / "takes" / f"{t.name}.h5").stat().st_size
    norm = sync_capture(cap, SyncSettings(**{**base.__dict__, "normalize_impulse": True}), progress=False)
    tn = norm.ok[1]
    assert tn.impulse_scale == pytest.approx(norm.reference_impulse_n_s / tn.impulse_n_s)
    assert abs(tn.impulse_scale - 1) > 0.02  # the hits differed in force
    with AlignedTake(cap, cap.paths.root / tn.aligned_file) as a:
        scaled = a.read_frames()
    rest = whole[:5].mean(axis=0)
    moved = np.abs(whole[-20:] - rest) > 30  # pixels that clearly changed
    ratio = np.median((scaled[-20:] - rest)[moved] / (whole[-20:] - rest)[moved])
    assert ratio == pytest.approx(tn.impulse_scale, rel=0.05)


def _rewrite_take(src: Capture, dst: Capture, name: str, new_name: str, *, force_scale: float) -> None:
    """A copy of a take with its force channel scaled: how a take with no hit in it looks."""
    with src.open_take(name) as r:
        w = dst.new_take(new_name, view=r.view, frame_shape=r.frame_shape, dtype=r.frames.dtype, bit_depth=r.bit_depth,
                         fps=r.fps, daq_t0_s=r.daq_t0_s, channels=[r.channel_info(n) for n in r.channel_names])
        with w:
            w.append_samples({n: r.channel(n) * (force_scale if n == "force" else 1.0) for n in r.channel_names})
            w.append_frames(r.read_frames(), r.frame_times_s, r.frame_counter)
            w.set_trigger(r.trigger)
            w.set_qc(r.qc)
            w.finalize()


def test_no_hit_is_excluded_not_guessed_and_no_tags_is_a_flag(sim_capture, tmp_path):
    cap = _copy(sim_capture, tmp_path / "cap")
    _rewrite_take(sim_capture, cap, "v00_000", "nohit", force_scale=0.0)
    res = sync_capture(cap, SyncSettings(takes="all", write_frames=False, check_with_image=False), progress=False)
    nohit = next(t for t in res.takes if t.name == "nohit")
    assert nohit.status == "excluded" and nohit.error == "force: no hit found: the force peaks at 0 N, below 5 N"
    # A layout that does not match the tags in view: timing needs no tags, so every take with a hit is still
    # synced, as well as before, and flagged for the pose stage (which cannot locate it).
    before = {t.name: t.offset_s for t in res.ok}
    m = cap.manifest
    for tag in m.tags.tags:
        tag.id += 1000
    cap.save_manifest()
    run = subprocess.run([sys.executable, "-m", "odsplat", "sync", str(cap.root), "--no-frames", "--all-takes"],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    after = load_sync(cap)
    assert {t.name for t in after.ok} == set(before) and len(before) == 5  # all but the double hit and the no-hit copy
    for t in after.ok:
        assert "no_tags_visible" in t.flags and t.tags_seen == [] and t.offset_s == pytest.approx(before[t.name])
    assert "EXCLUDED: no AprilTag" not in run.stdout


def test_cli_sync_writes_json_and_plot(sim_capture, tmp_path):
    cap = _copy(sim_capture, tmp_path / "cap")
    run = subprocess.run([sys.executable, "-m", "odsplat", "sync", str(cap.root), "--no-frames",
                          "--trigger-delay-s", str(TRIGGER_DELAY_S)], capture_output=True, text=True, cwd=REPO,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "4/4 takes synced" in run.stdout
    assert (cap.derived_dir / "sync.png").stat().st_size > 10_000
    assert not (cap.derived_dir / "sync").exists()
    bad = subprocess.run([sys.executable, "-m", "odsplat", "sync", str(cap.root), "--method", "strobe"],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert bad.returncode == 2 and "strobe" in bad.stderr

