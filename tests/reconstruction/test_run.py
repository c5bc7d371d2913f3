"""The whole reconstruction stage on a small simulated capture, through the command line: sync, magnify, poses,
reconstruct, render; the saved files and their errors."""
from __future__ import annotations

import json
import re
import shutil

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from odsplat.acquisition.plan import PlanSettings
from odsplat.acquisition.session import CaptureSession, SessionSettings
from odsplat.acquisition.trigger import HammerTrigger
from odsplat.app.cli import main
from odsplat.hil_sim.bench import SimBench, SimBenchSettings
from odsplat.reconstruction.gaussians import load_ply
from odsplat.reconstruction.model import DynamicScene, ReconstructSettings, parse_times
from odsplat.reconstruction.views import select_frames
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture


def _ok(args):
    r = CliRunner().invoke(main, [str(a) for a in args])
    assert r.exit_code == 0, r.output + repr(r.exception)
    return r.output


@pytest.fixture(scope="module")
def reconstructed(tmp_path_factory):
    """Twelve views (twelve frames, four before the hit) and static photos, through every stage to the model."""
    out = tmp_path_factory.mktemp("recon") / "cap"
    session = SessionSettings(name="cap", plan=PlanSettings(n_views=12), n_frames=12, pretrigger_frames=4,
                              trigger=HammerTrigger(pretrigger_s=0.01, record_s=0.05), static_photos=True)
    assert CaptureSession(out, session, SimBench(settings=SimBenchSettings(seed=1))).run().complete
    _ok(["sync", out])
    _ok(["magnify", out, "--alpha", "20", "--workers", "1", "--every-view"])
    _ok(["poses", out])
    text = _ok(["reconstruct", out, "--motion", "timestep", "--width", "64", "--timesteps", "3", "--iters-t0", "150",
                "--iters-step", "15", "--holdout", "v05_000", "--threads", "1"])
    return Capture.open(out), text


def test_reconstruct_writes_the_model(reconstructed):
    cap, text = reconstructed
    d = cap.derived_dir / "reconstruction"
    report = json.loads((d / "reconstruction.json").read_text())
    assert report["kind"] == "odsplat.reconstruction" and report["capture_id"] == cap.id
    assert "v05_000" not in report["views"] and len(report["views"]) == 11 and len(report["static"]) == 12
    assert report["holdout"] == ["v05_000"] and len(report["times_s"]) == 3 and report["times_s"][0] < 0
    # The rest fit explains the training views; a few iterations already beat a flat grey image by far.
    assert report["result"]["psnr_t0_db"] > 20.0
    scene = DynamicScene.load(cap)
    n = len(scene.means_rest_m)
    assert scene.displacement_m.shape == (3, n, 3) and scene.quats.shape == (3, n, 4)
    assert np.all(scene.displacement_m[0] == 0)
    # The .ply holds the same rest state, in metres, in the world frame of the tags (floor z = 0).
    g = load_ply(d / "gaussians_t0.ply", n_colors=1)
    assert len(g) == n and np.allclose(g.means.numpy(), scene.means_rest_m, atol=1e-5)
    opaque = torch.sigmoid(g.opacity_logits).numpy() > 0.5
    assert np.median(np.abs(g.means.numpy()[opaque, 2])) < 0.5  # the rig is about 1 m tall, the floor at 0
    assert f"{n} Gaussians from 11 views (+12 static) over 3 timesteps" in text


def test_render_a_take_camera_matches_its_frame(reconstructed, tmp_path):
    cap, _ = reconstructed
    _ok(["render", cap.root, "--camera", "v03_000", "--times", "all", "--width", "64", "-o", tmp_path / "r"])
    pngs = sorted((tmp_path / "r").glob("frame_*.png"))
    assert len(pngs) == 3 and (tmp_path / "r" / "render.mp4").stat().st_size > 0
    img = cv2.imread(str(pngs[0]), cv2.IMREAD_UNCHANGED).astype(float) / 255
    from odsplat.processing import MagnifiedVideo
    with MagnifiedVideo(cap.derived_dir / "magnified" / "phase" / "v03_000.h5") as f:
        frame = f.read_frames(int(select_frames(f.times_s, 3)[0]))[0] / (2 ** int(f.attrs["bit_depth"]) - 1)
    small = cv2.resize(frame.astype(np.float32), (64, 48), interpolation=cv2.INTER_AREA)
    psnr = 10 * np.log10(1 / np.mean((img - small) ** 2))
    assert img.shape == (48, 64) and psnr > 20.0, psnr


def test_render_held_out_view_and_orbit(reconstructed, tmp_path):
    cap, _ = reconstructed
    # The held-out take was never trained on; its estimated pose still renders a plausible image.
    _ok(["render", cap.root, "--camera", "v05_000", "--times", "0", "--width", "64", "-o", tmp_path / "h", "--no-mp4"])
    img = cv2.imread(str(tmp_path / "h" / "frame_0000.png"), cv2.IMREAD_UNCHANGED)
    assert img.std() > 10 and not (tmp_path / "h" / "render.mp4").exists()
    out = _ok(["render", cap.root, "--camera", "orbit:5:40", "--times", "0", "--width", "48", "-o", tmp_path / "o"])
    assert "5 frames" in out and len(list((tmp_path / "o").glob("*.png"))) == 5


def test_modal_model_on_raw_frames_and_magnification_at_render(reconstructed, tmp_path):
    cap, _ = reconstructed
    # The same capture, the modal model on sync's unmagnified frames (a copy: the fixture's model stays).
    raw = tmp_path / "raw"
    shutil.copytree(cap.root, raw)
    text = _ok(["reconstruct", raw, "--source", "sync", "--motion", "modal", "--components", "2", "--width", "64",
                "--timesteps", "3", "--iters-t0", "100", "--iters-modal", "30", "--threads", "1"])
    assert "over 3 timesteps" in text
    report = json.loads((raw / "derived" / "reconstruction" / "reconstruction.json").read_text())
    assert report["motion"] == "modal" and report["source_alpha"] == 1.0
    assert len(report["modal"]["energy_share"]) == 2
    scene = DynamicScene.load(Capture.open(raw))
    assert scene.motion == "modal" and scene.basis.shape == (3, 2)
    assert np.allclose(np.einsum("tk,nkc->tnc", scene.basis, scene.shapes_m), scene.displacement_m, atol=1e-6)
    # The fixture's model was trained on frames magnified 20x in 2D: its physical displacement divides that out.
    mag = DynamicScene.load(cap)
    assert mag.source_alpha == 20.0 and mag.motion == "timestep"
    assert np.allclose(mag.physical_displacement_m(), mag.displacement_m / 20.0)
    # --alpha at render time: 0 shows the rest state at every time, 60 three times the trained motion.
    t = float(mag.times_s[-1])
    _ok(["render", cap.root, "--camera", "v03_000", "--times", f"{t},{mag.times_s[0]}", "--alpha", "0", "--width",
         "64", "-o", tmp_path / "a0", "--no-mp4"])
    a, b = (cv2.imread(str(tmp_path / "a0" / f"frame_000{k}.png"), cv2.IMREAD_UNCHANGED) for k in (0, 1))
    assert np.array_equal(a, b)
    means, _ = mag.state(t, alpha=60.0)
    rest = mag.scene.to_scene(mag.means_rest_m)
    assert np.allclose(means.numpy() - rest, 3 * mag.scene.to_scene(mag.means_rest_m + mag.displacement_m[-1])
                       - 3 * rest, atol=1e-5)
    r = CliRunner().invoke(main, ["render", str(cap.root), "--camera", "v03_000", "--alpha", "-1"])
    assert r.exit_code == 2 and "--alpha" in r.output


def test_linear_motion_is_the_default_of_the_command_line(reconstructed, tmp_path):
    cap, _ = reconstructed
    raw = tmp_path / "lin"
    shutil.copytree(cap.root, raw)
    text = _ok(["reconstruct", raw, "--width", "64", "--timesteps", "8", "--iters-t0", "100", "--threads", "1"])
    assert "over 8 timesteps" in text
    report = json.loads((raw / "derived" / "reconstruction" / "reconstruction.json").read_text())
    assert report["motion"] == "linear" and report["settings"]["source"] == "sync" and report["source_alpha"] == 1.0
    lin = report["linear"]
    assert lin["n_nodes"] > 10 and lin["n_pixels"] > 1000 and len(lin["views"]) == 12
    scene = DynamicScene.load(Capture.open(raw))
    assert scene.motion == "modal" and scene.basis.shape[0] == 8
    assert np.all(scene.displacement_m[0] == 0)
    # Physical motion of a structure hit by a hand hammer: micrometres, not millimetres.
    assert 0 < np.abs(scene.displacement_m).max() < 2e-3
    # Beside the model, its node graph's unfiltered motion (every temporal component) for the analysis' fits.
    with np.load(raw / "derived" / "reconstruction" / "measured_motion.npz") as z:
        assert z["displacement_m"].shape == (8, lin["n_nodes"], 3) and np.allclose(z["times_s"], scene.times_s)
        assert float(z["source_alpha"]) == 1.0 and 0 < np.abs(z["displacement_m"]).max() < 2e-3
    assert not (cap.derived_dir / "reconstruction" / "measured_motion.npz").exists()   # the per-timestep model
    r = CliRunner().invoke(main, ["reconstruct", str(raw), "--motion", "linear", "--source", "magnified/phase"])
    assert r.exit_code == 2 and "sync" in r.output


def test_render_errors(reconstructed, tmp_path):
    cap, _ = reconstructed
    r = CliRunner().invoke(main, ["render", str(cap.root), "--camera", "nope", "--times", "0"])
    assert r.exit_code == 2 and "nope" in r.output
    r = CliRunner().invoke(main, ["render", str(cap.root), "--times", "1:2"])
    assert r.exit_code == 2 and "--times" in r.output
    r = CliRunner().invoke(main, ["render", str(cap.root), "--camera", "orbit:3", "--times", "0,0.0005"])
    assert r.exit_code == 2 and "3 cameras and 2 times" in r.output
    bare = tmp_path / "bare"
    shutil.copytree(cap.root, bare, ignore=shutil.ignore_patterns("derived"))
    with pytest.raises(InputError, match="trajectories.npz"):
        DynamicScene.load(Capture.open(bare))
    r = CliRunner().invoke(main, ["reconstruct", str(bare)])
    assert r.exit_code == 2 and "poses.json" in r.output


def test_parse_times_and_frame_selection():
    trained = np.array([-0.0002, 0.0003, 0.0008])
    assert np.allclose(parse_times("all", trained), trained)
    assert np.allclose(parse_times("0:0.0008:3", trained), [0, 0.0004, 0.0008])
    assert np.allclose(parse_times("0.0001, -0.0002", trained), [0.0001, -0.0002])
    for spec in ("soon", "nan", "0:nan:3", "1e9", "0.0009", "-1:0:2"):
        with pytest.raises(InputError, match="--times"):
            parse_times(spec, trained)
    times = np.arange(-3, 7) * 5e-4
    assert list(select_frames(times, 3)) == [2, 3, 4]          # from the last frame before the impact
    assert list(select_frames(times, 3, step=2, start=1)) == [1, 3, 5]
    with pytest.raises(InputError, match="run past"):
        select_frames(times, 8, step=2)
    # By default the record: every frame from the rest frame to the grid's end (the linear and modal models fit
    # them at once), at most max_timesteps; the per-timestep fits keep 32.
    assert list(select_frames(times, None)) == list(range(2, 10))
    assert list(select_frames(times, None, step=3)) == [2, 5, 8]
    assert list(select_frames(times, None, max_timesteps=4)) == [2, 3, 4, 5]
    assert ReconstructSettings().timesteps is None and ReconstructSettings(motion="modal").timesteps is None
    assert ReconstructSettings(motion="timestep").timesteps == 32
    assert ReconstructSettings(n_timesteps=5, motion="timestep").timesteps == 5


def test_a_reconstruction_from_magnified_frames_stops_where_views_were_not_magnified(reconstructed, tmp_path):
    """magnify does the first view only unless told (issue 44): the paper's order, reconstructing from magnified
    frames, must not train on that one view in silence. One line naming the takes and the command, status 2."""
    cap, _ = reconstructed
    copy = tmp_path / "cap"
    shutil.copytree(cap.root, copy)
    _ok(["magnify", copy, "--alpha", "20", "--workers", "1", "--no-video"])        # the default: the first view
    r = CliRunner().invoke(main, ["reconstruct", str(copy), "--motion", "timestep", "--width", "48",
                                  "--timesteps", "2", "--iters-t0", "10", "--threads", "1"])
    assert r.exit_code == 2, r.output
    line = r.output.strip().splitlines()[-1]
    m = re.search(r"no magnified/phase frames for (\d+) of the (\d+) posed takes \(v", line)
    assert m and int(m.group(1)) == int(m.group(2)) - 1 >= 10, r.output
    assert "run `odsplat magnify --every-view` first" in line and "Traceback" not in r.output
