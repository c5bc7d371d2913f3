"""One camera, no force (issue 45): a hil_sim video of the arm, filmed alone, goes `odsplat import` -> `odsplat run`
-> report, and its modes and 2D shapes are scored against the truth projected into the view."""
from __future__ import annotations

import re
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from odsplat.analysis.video2d import read_video2d
from odsplat.hil_sim.video import VideoSimSettings, VideoTruth, simulate_video
from odsplat.spine.store import Capture

from .test_mp4_browser import _chromium, chromium_plays

SIM = VideoSimSettings(width_px=192, height_px=144, supersample=2, n_frames=768, fps=1000.0, excitation="hit",
                       peak_n=1500.0)


def _odsplat(*args: str) -> subprocess.CompletedProcess:
    run = subprocess.run([sys.executable, "-m", "odsplat", *args], capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    return run


@pytest.fixture(scope="module")
def video_capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("video2d")
    rig = simulate_video(root / "sim", SIM)
    cap = root / "cap"
    _odsplat("import", str(rig), "-o", str(cap))
    # short clips: the clip's length is not what is tested
    (cap / "odsplat.toml").write_text("[analyze.video2d]\nclip_frames = 48\n")
    run = _odsplat("run", str(cap))
    return Capture.open(cap), VideoTruth.load(root / "sim" / "truth.npz"), run.stdout


def test_qc_keeps_the_video_and_sync_keeps_its_frame_times(video_capture):
    capture, _, out = video_capture
    assert "[magnify] does not apply: no force" in out
    qc = (capture.paths.qc_json).read_text()
    assert '"content": "frames"' in qc and '"status": "accepted"' in qc
    sync = capture.paths.sync_json.read_text()
    assert '"method": "frames"' in sync and "no_force" in sync


def test_the_scale_comes_from_the_tags_in_the_view_at_their_depth(video_capture):
    """At 192x144 px the structure's 6 cm tags are too small to find; floor tags are found, and the scale is theirs
    (said so: true at their depth)."""
    capture, truth, _ = video_capture
    doc, _ = read_video2d(capture)
    tags = {t.id: t for t in capture.manifest.tags.tags}
    seen = [n for n in doc["notes"] if n.startswith("scale ")]
    assert seen and "true at their depth" in seen[0], doc["notes"]
    ids = [int(i) for i in re.search(r"tag\(s\) \[([0-9, ]+)\]", seen[0]).group(1).split(",")]
    # the true scale at those tags: their depth over the focal length
    centres = np.array([np.mean(tags[i].corners_m, axis=0) for i in ids])
    depth = (centres @ truth.R.T + truth.t)[:, 2]
    true = depth / truth.K[0, 0]
    # measured 5.25 mm/px against 5.28-5.34 (the tags' homography, scale along their unforeshortened axis)
    assert true.min() * 0.95 < doc["scale_m_per_px"] < true.max() * 1.05, (doc["scale_m_per_px"], true)


def test_frequencies_and_2d_shapes_match_the_projected_truth(video_capture):
    capture, truth, _ = video_capture
    doc, arrays = read_video2d(capture)
    # the modes (stable SSI poles) above the floor; FDD peaks no pole explains are ODS lines, not modes
    judged = [k for k, m in enumerate(doc["modes"]) if m["above_floor"] and m["kind"] == "mode"]
    assert len(judged) >= 3, doc["modes"]
    points = arrays["points_px"][arrays["moving"]]
    projected = truth.image_shapes(points)                      # (n_modes, P, 2)
    found = set()
    for k in judged:
        f = doc["modes"][k]["freq_hz"]
        j = int(np.argmin(np.abs(truth.freqs_hz - f)))
        assert abs(f / truth.freqs_hz[j] - 1) < 0.01, (f, truth.freqs_hz[j])
        a, b = projected[j].reshape(-1), arrays["shapes"][k].reshape(-1)
        mac = abs(np.vdot(a, b)) ** 2 / (np.vdot(a, a).real * np.vdot(b, b).real)
        assert mac >= 0.95, (f, mac)
        found.add(j)
    assert {0, 1, 2} <= found   # the arm's 23.5, 31 and 86 Hz modes, which this view and hit show


def test_the_report_shows_each_mode_with_a_clip_that_a_browser_plays(video_capture, tmp_path):
    capture, _, _ = video_capture
    doc, _ = read_video2d(capture)
    html = capture.paths.report_html.read_text()
    judged = [m for m in doc["modes"] if m["above_floor"]]
    assert html.count("<video") == len(judged) and html.count("data:video/mp4;base64,") == len(judged)
    assert all(m["clip"] for m in judged)
    clip = capture.paths.analysis_dir / judged[0]["clip"]
    if _chromium() is None:
        pytest.skip("no chromium on PATH: the clip's playback is checked where there is one")
    result = chromium_plays(clip, tmp_path)
    assert result.startswith("PLAYED "), result


def test_odsplat_view_shows_a_mode_on_the_frame(video_capture, tmp_path):
    """`odsplat view` on a capture the 2D path analysed: the first frame with a mode's shape drawn, magnified so that
    its largest arrow is 5 % of the frame's width; one cycle as a GIF; no window (issue 46)."""
    cap, _, _ = video_capture
    from click.testing import CliRunner

    from odsplat.app.cli import main
    png, gif = tmp_path / "v.png", tmp_path / "v.gif"
    res = CliRunner().invoke(main, ["view", str(cap.root), "--screenshot", str(png), "--mode", "1"])
    assert res.exit_code == 0, res.output
    img = np.asarray(Image.open(png).convert("RGB"), int)
    assert img.shape == (SIM.height_px, SIM.width_px, 3)
    coloured = np.abs(img[..., 0] - img[..., 2]) > 40            # the arrows: the frame itself is grey
    assert coloured.sum() > 50
    res = CliRunner().invoke(main, ["view", str(cap.root), "--export", str(gif), "--frames", "6"])
    assert res.exit_code == 0 and Image.open(gif).n_frames == 6, res.output
    res = CliRunner().invoke(main, ["view", str(cap.root), "--screenshot", str(png), "--mode", "99"])
    assert res.exit_code == 2 and "--mode" in res.output and "Traceback" not in res.output, res.output


def test_the_tacoma_footage_gives_one_clear_peak_and_its_amplified_clip(shared_data, tmp_path):
    """Archive footage (pyidi's sample, 248 frames at 30 fps): no pole stands stable in 8 cycles, so the dominant
    oscillation comes out as the FDD's peak, its ODS above the floor, with a clip."""
    (tmp_path / "rig.toml").write_text('name = "tacoma"\n\n[[takes]]\nname = "bridge"\nview = 0\n'
                                       'video = "tacoma_bridge.mp4"\n')
    cap = tmp_path / "cap"
    _odsplat("import", str(tmp_path / "rig.toml"), "-o", str(cap), "--data", str(shared_data / "pyidi-samples"))
    (cap / "odsplat.toml").write_text("[analyze.video2d]\nclip_frames = 32\nmax_points = 60\n")
    _odsplat("run", str(cap))
    doc, _ = read_video2d(Capture.open(cap))
    above = [m for m in doc["modes"] if m["above_floor"]]
    assert len(above) == 1 and 0.8 < above[0]["freq_hz"] < 1.1, doc["modes"]
    assert above[0]["clip"] and (cap / "derived" / "analysis" / above[0]["clip"]).stat().st_size > 10_000
