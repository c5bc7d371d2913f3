"""The magnify stage's mp4s, `odsplat export-video`, and the motion limit: on the simulated rig (sub-pixel motion,
its ground truth) and on the real Tacoma Narrows clip (motion of tens of pixels)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from odsplat.app.pipeline import Stamp, run_stage
from odsplat.processing import MagnifiedVideo, MagnifyResult, MagnifySettings, export_video, magnify_capture
from odsplat.spine.importer import import_capture
from odsplat.spine.mp4 import count_frames, display_range, read_comment, to_8bit
from odsplat.spine.store import Capture
from odsplat.sync import SyncSettings, sync_capture

from ..conftest import TRIGGER_DELAY_S

REPO = Path(__file__).resolve().parents[2]
TAKE = "v03_000"


@pytest.fixture(scope="module")
def synced(sim_capture, tmp_path_factory) -> Capture:
    dest = tmp_path_factory.mktemp("video") / "cap"
    shutil.copytree(sim_capture.root, dest, ignore=shutil.ignore_patterns("derived"))
    cap = Capture.open(dest)
    sync_capture(cap, SyncSettings(camera_trigger_delay_s=TRIGGER_DELAY_S, check_with_image=False), progress=False)
    return cap


def _decoded_grey(path: Path) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while (frame := cap.read()[1]) is not None:
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    cap.release()
    return np.stack(frames)


def _true_motion_px(cap: Capture, take: str) -> float:
    """The rig's largest image motion in the take: its surface points moved by their modal motion, projected."""
    z = np.load(cap.root / "takes" / f"{take}.truth.npz")
    k, r, t = z["camera_K"], z["camera_R"], z["camera_t"]

    def project(x: np.ndarray) -> np.ndarray:
        u = (x @ r.T + t) @ k.T
        return u[..., :2] / u[..., 2:]

    moved = z["surface_points_m"][None] + np.einsum("pmk,mf->fpk", z["surface_mode_shapes"], z["modal_q_frames"])
    return float(np.linalg.norm(project(moved) - project(z["surface_points_m"]), axis=2).max())


def test_magnify_writes_an_mp4_per_take_with_its_stamp_and_limit(synced):
    settings = MagnifySettings(method="phase", alpha=30.0, takes=(TAKE,), workers=1)
    run = run_stage(synced, "magnify", settings=settings)
    res = run.result
    t = res.takes[0]
    path = synced.paths.magnified_video("phase", TAKE)
    assert t.video["file"] == "magnified/phase/v03_000.mp4" and path.is_file()
    assert "magnified/phase/v03_000.mp4" in Stamp.read(synced, "magnify").outputs   # the pipeline vouches for it
    listed = json.loads(synced.paths.magnify_json("phase").read_text())["takes"][0]
    assert listed["video"]["recorded_fps"] == pytest.approx(2000.0) and listed["video"]["fps"] == 30.0
    comment = read_comment(path)
    assert "recorded at 2000 frames/s, played at 30 frames/s (66.67x slower)" in comment, comment
    with MagnifiedVideo(synced.paths.root / t.file) as mag:
        expected = to_8bit(mag.read_frames(), tuple(t.video["dn_range"]))
    decoded = _decoded_grey(path)
    assert count_frames(path) == len(decoded) == len(expected) == t.n_frames > 50
    assert decoded.shape[1:] == expected.shape[1:] == (300, 400)
    corr = min(np.corrcoef(a.ravel(), b.ravel())[0, 1] for a, b in zip(decoded.astype(float), expected))
    print("mp4 bytes", t.video["bytes"], "lowest frame correlation", corr)
    assert corr > 0.97, corr          # measured 0.997 (H.264, CRF 18)

    # The measured motion is the rig's (0.14 px at the column's top): alpha 30 passes the phase bound at the 4 px
    # band (30 x 0.13 > 1 px); the alpha it names fits, and magnifying by it does not warn.
    truth = _true_motion_px(synced, TAKE)
    assert t.limit["motion_px"] == pytest.approx(truth, rel=0.25), (t.limit, truth)
    assert t.limit["passes"] and t.warning.startswith("v03_000: alpha 30 x 0.1")
    fits = t.limit["fits_alpha"]
    assert 5.0 < fits < 12.0 and f"alpha <= {int(fits)}" in t.warning, t.warning
    quiet = magnify_capture(synced, MagnifySettings(method="phase", alpha=int(fits), takes=(TAKE,), workers=1,
                                                    video=False), progress=False)
    assert not quiet.takes[0].limit["passes"] and quiet.takes[0].warning is None
    assert not path.exists() and quiet.takes[0].video is None       # video off: the old mp4 is pruned


def test_side_by_side_shows_the_input_left(synced):
    res = magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, takes=(TAKE,), workers=1,
                                                  side_by_side=True, video_fps=10.0), progress=False)
    v = res.takes[0].video
    decoded = _decoded_grey(synced.paths.root / v["file"])
    assert decoded.shape == (res.takes[0].n_frames, 300, 800) and v["side_by_side"] and v["fps"] == 10.0
    raw = export_video(synced, TAKE, "sync", fps=10.0)
    left = _decoded_grey(raw.mp4.path)
    assert np.corrcoef(left[30].ravel(), decoded[30, :, :400].ravel().astype(float))[0, 1] > 0.97


@pytest.mark.parametrize("source", ["raw", "sync", "magnified/linear"])
def test_export_video_from_each_source(synced, source, tmp_path):
    if source.startswith("magnified/"):
        magnify_capture(synced, MagnifySettings(method="linear", alpha=4.0, takes=(TAKE,), workers=1, video=False),
                        progress=False)
    out = tmp_path / "x.mp4"
    run = subprocess.run([sys.executable, "-m", "odsplat", "export-video", str(synced.root), "--take", TAKE,
                          "--source", source, "-o", str(out), "--fps", "25"],
                         capture_output=True, text=True, cwd=REPO, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    with Capture.open(synced.root).open_take(TAKE) as r:
        n = r.n_frames if source == "raw" else MagnifyResult.read(synced, "linear").takes[0].n_frames
    assert count_frames(out) == n and f"{n} frames 400x300 px" in run.stdout
    assert "played at 25 frames/s" in read_comment(out)
    if source == "magnified/linear":   # no video from the stage: the first 16 frames' percentiles
        t = MagnifyResult.read(synced, "linear").takes[0]
        with MagnifiedVideo(synced.paths.root / t.file) as mag:
            want = to_8bit(mag.read_frames(40, 41), display_range(mag.read_frames(0, 16)))
        assert np.corrcoef(_decoded_grey(out)[40].ravel(), want[0].ravel())[0, 1] > 0.97


@pytest.mark.parametrize("args, message", [
    (["--take", "nope"], "--take: no take 'nope'"),
    (["--take", TAKE, "--source", "magnified/fancy"], "--source: expected one of"),
    (["--take", TAKE, "--fps", "0"], "--fps: expected a playback rate > 0"),
    (["--take", TAKE, "--fps", "-3"], "--fps: expected a playback rate > 0"),
    (["--take", TAKE, "-o", "EXISTING"], "exists already"),
])
def test_export_video_bad_input_is_one_line(synced, tmp_path, args, message):
    existing = tmp_path / "old.mp4"
    existing.write_bytes(b"keep")
    args = [str(existing) if a == "EXISTING" else a for a in args]
    before = sorted(p for p in synced.paths.root.rglob("*"))
    run = subprocess.run([sys.executable, "-m", "odsplat", "export-video", str(synced.root), *args],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2 and message in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
    assert sorted(p for p in synced.paths.root.rglob("*")) == before and existing.read_bytes() == b"keep"


def test_tacoma_at_alpha_20_warns_and_names_an_alpha(shared_data, tmp_path):
    """The Tacoma Narrows film (334x250 px RGB, 30 fps; its first 90 frames, for the suite's time): the deck moves
    tens of pixels against the first frame, far past the phase method's bound at alpha 20; the warning says so
    and names the alpha that fits."""
    import cv2

    src = cv2.VideoCapture(str(shared_data / "pyidi-samples" / "tacoma_bridge.mp4"))
    size = (int(src.get(cv2.CAP_PROP_FRAME_WIDTH)), int(src.get(cv2.CAP_PROP_FRAME_HEIGHT)))
    out = cv2.VideoWriter(str(tmp_path / "tacoma.avi"), cv2.VideoWriter.fourcc(*"MJPG"), src.get(cv2.CAP_PROP_FPS),
                          size)
    for _ in range(90):
        ok, frame = src.read()
        assert ok
        out.write(frame)
    out.release()
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "tacoma"\n[[takes]]\nname = "tacoma"\nvideo = "tacoma.avi"\n')
    cap = import_capture(rig, tmp_path / "cap")
    res = magnify_capture(cap, MagnifySettings(method="phase", alpha=20.0, source="raw", takes=("tacoma",),
                                               workers=1), progress=False)
    t = res.takes[0]
    assert t.limit["passes"] and t.limit["motion_px"] > 10.0, t.limit       # measured 21.6 px (25.9 over all 248)
    fits = t.limit["fits_alpha"]
    assert fits * t.limit["motion_px"] == pytest.approx(1.0) and fits < 0.1
    assert t.warning.startswith("tacoma: alpha 20 x 2") and f"only alpha <= {fits:.2g} fits" in t.warning, t.warning
    assert f"warning: {t.warning}" in res.summary()
    assert count_frames(cap.paths.magnified_video("phase", "tacoma")) == 90
