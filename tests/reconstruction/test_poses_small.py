"""Poses at low resolution with small floor tags (256x192 px, tags 12-25 px), the tag-only fallback with single
tags and its per-image reasons, and known cameras read with `--from FILE`; all against hil_sim's true poses."""
from __future__ import annotations

import json
import shutil
import time

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from odsplat.acquisition.plan import PlanSettings
from odsplat.acquisition.session import CaptureSession, SessionSettings
from odsplat.acquisition.trigger import HammerTrigger
from odsplat.app.cli import main
from odsplat.app.config import load_config
from odsplat.app.pipeline import run_stage
from odsplat.hil_sim.bench import SimBench, SimBenchSettings
from odsplat.hil_sim.rig import TakeTruth, truth_path
from odsplat.reconstruction.pose_result import PoseResult, PoseSettings
from odsplat.reconstruction.poses import estimate_poses
from odsplat.reconstruction.sim3 import compare_poses
from odsplat.spine.geometry import camera_center_m
from odsplat.spine.store import Capture
from odsplat.spine.tags import detect_tags

N_VIEWS = 12
WIDTH, HEIGHT = 256, 192  # fov 50 deg, 1.6 m from the target: the 0.12 m floor tags are 12 to 25 px across
# Measured on this capture (docs/poses.md): SfM 24/24 registered, rotation 0.18 deg rms (0.40 max), centre 5.3 mm
# rms (10.4 max, 0.58 % of the 1.8 m camera distance). The issue asks for < 1 deg and < 2 %.
ROT_MAX_DEG = 1.0
CENTER_MAX_FRACTION = 0.015


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory) -> Capture:
    """Twelve views at 256x192 px, each with a take of four frames and a still photo (about 7 s)."""
    out = tmp_path_factory.mktemp("small") / "cap"
    session = SessionSettings(name="cap", plan=PlanSettings(n_views=N_VIEWS), n_frames=4, pretrigger_frames=2,
                              trigger=HammerTrigger(pretrigger_s=0.01, record_s=0.05), static_photos=True)
    report = CaptureSession(out, session, SimBench(settings=SimBenchSettings(seed=1, width_px=WIDTH,
                                                                             height_px=HEIGHT))).run()
    assert report.complete
    cap = Capture.open(out)
    # The first symptom of the issue: takes rejected because the small tags were not found.
    rejected = [t.name for t in cap.manifest.takes if "tags_not_visible" in json.dumps(t.qc)]
    assert not rejected, rejected
    return cap


def _copy(cap: Capture, root) -> Capture:
    root.mkdir(parents=True)
    shutil.copytree(cap.takes_dir, root / "takes")
    shutil.copytree(cap.static_dir, root / "static")
    shutil.copy(cap.root / "capture.json", root / "capture.json")
    return Capture.open(root)


def _truth(cap: Capture) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for record in cap.manifest.takes:
        tr = TakeTruth.load(truth_path(cap.root / record.file))
        out[record.name] = (tr.camera_R, tr.camera_t)
        out[f"static/view_{record.view:02d}"] = (tr.camera_R, tr.camera_t)
    return out


def _distance_m(truth) -> float:
    return float(np.mean([np.linalg.norm(camera_center_m(R, t)) for R, t in truth.values()]))


def test_small_capture_is_posed_with_the_defaults(small_capture, tmp_path):
    cap = _copy(small_capture, tmp_path / "cap")
    t0 = time.perf_counter()
    result = estimate_poses(cap)
    elapsed_s = time.perf_counter() - t0
    truth = _truth(cap)
    acc = compare_poses(result.poses(), truth)
    distance = _distance_m(truth)
    print(f"{WIDTH}x{HEIGHT}, {result.n_images} images in {elapsed_s:.1f} s: {result.reason}; {acc.summary()}; "
          f"centre max {acc.center_max_mm / 1e3 / distance:.2%} of {distance:.2f} m")
    assert len(result.views) >= 0.9 * len(truth) and result.n_images == len(truth)
    assert acc.rotation_max_deg < ROT_MAX_DEG
    assert acc.center_max_mm / 1e3 < CENTER_MAX_FRACTION * distance
    assert result.method == "sfm" and result.sim3_corners >= 12  # metric by the triangulated tag corners
    assert any("held at their layout positions" in n for n in result.notes)
    assert not result.unposed


def _only_tag(image: np.ndarray, keep: int | None) -> np.ndarray:
    """The image with every floor tag but `keep` painted over in the floor's grey (None: all of them)."""
    out = image.copy()
    for d in detect_tags(image):
        if d.id == keep:
            continue
        c = d.corners_px.mean(0)
        quad = c + 1.6 * (d.corners_px - c)  # the quiet zone too
        cv2.fillConvexPoly(out, np.round(quad).astype(np.int32), int(np.median(image)))
    return out


def test_fallback_poses_single_tags_and_says_why_an_image_is_not_posed(small_capture, tmp_path):
    """SfM gets no features (every mask black); one photo keeps a single tag, one none at all."""
    cap = _copy(small_capture, tmp_path / "cap")
    one, none = cap.static_dir / "view_02.png", cap.static_dir / "view_05.png"
    img = cv2.imread(str(one), cv2.IMREAD_UNCHANGED)
    ids = [d.id for d in detect_tags(img)]
    cv2.imwrite(str(one), _only_tag(img, ids[0]))
    cv2.imwrite(str(none), _only_tag(cv2.imread(str(none), cv2.IMREAD_UNCHANGED), None))
    masks = tmp_path / "masks"
    (masks / "static").mkdir(parents=True)
    for name in cap.take_names():
        cv2.imwrite(str(masks / f"{name}.png"), np.zeros((HEIGHT, WIDTH), np.uint8))
    for photo in cap.static_dir.glob("*.png"):
        cv2.imwrite(str(masks / "static" / photo.name), np.zeros((HEIGHT, WIDTH), np.uint8))
    result = estimate_poses(cap, PoseSettings(masks_dir=masks))
    truth = _truth(cap)
    assert result.method == "tags" and "SfM" in result.reason
    assert set(result.unposed) == {"static/view_05"}
    assert result.unposed["static/view_05"].startswith("no floor tag of the layout detected; SfM: no verified")
    assert any("not posed: static/view_05: no floor tag" in line for line in result.report_lines())
    assert any("one floor tag alone" in n and "static/view_02" in n for n in result.notes)
    acc = compare_poses(result.poses(), truth)
    distance = _distance_m(truth)
    print(f"tag-only fallback at {WIDTH}x{HEIGHT}: {acc.summary()}; single tag (static/view_02): "
          f"{acc.rotation_deg['static/view_02']:.3f} deg, {acc.center_mm['static/view_02']:.1f} mm")
    assert len(result.views) == len(truth) - 1
    assert acc.rotation_max_deg < ROT_MAX_DEG and acc.center_max_mm / 1e3 < CENTER_MAX_FRACTION * distance
    result.write(cap)
    doc = json.loads(cap.paths.poses_json.read_text())
    assert doc["unposed"] == [{"name": "static/view_05", "reason": result.unposed["static/view_05"]}]
    assert PoseResult.read(cap).unposed == result.unposed


def _pose_file(cap: Capture, path, names=None) -> None:
    lines = []
    for record in cap.manifest.takes:
        if names is not None and record.name not in names:
            continue
        tr = TakeTruth.load(truth_path(cap.root / record.file))
        lines += ["[[views]]", f'name = "{record.name}"', f"K = {np.asarray(tr.camera_K).tolist()}",
                  f"R = {np.asarray(tr.camera_R).tolist()}", f"t = {np.asarray(tr.camera_t).tolist()}", ""]
    path.write_text("\n".join(lines))


def test_known_cameras_from_a_file(small_capture, tmp_path):
    cap = _copy(small_capture, tmp_path / "cap")
    path = tmp_path / "rig.toml"
    _pose_file(cap, path)
    run = CliRunner().invoke(main, ["poses", str(cap.root), "--from", str(path)])
    assert run.exit_code == 0, run.output
    assert run.output.startswith("poses: method file (known cameras from ")
    result = PoseResult.read(cap)
    assert result.method == "file" and result.source == str(path)
    truth = _truth(cap)
    for name in cap.take_names():
        v = result.view(name)
        assert v.source == "file" and np.array_equal(v.R, truth[name][0]) and np.array_equal(v.t, truth[name][1])
    # The photos are not in the file: reported, not posed. The tags check the file's poses.
    assert set(result.unposed) == {n for n in truth if n.startswith("static/")}
    rot, mm = result.tag_agreement()
    print(f"tags vs the true poses read from the file, {len(rot)} views: {rot.max():.3f} deg, {mm.max():.1f} mm max")
    assert len(rot) == N_VIEWS and rot.max() < 0.5 and mm.max() < 15
    # The same through the configuration, as `odsplat run --set poses.from_file=...` does.
    config = load_config(cap, sets=(f"poses.from_file={json.dumps(str(path))}",))
    assert config.poses.from_file == path
    assert run_stage(cap, "poses", config).result.method == "file"


def test_a_bad_pose_file_is_refused_field_by_field(small_capture, tmp_path):
    cap = _copy(small_capture, tmp_path / "cap")
    good = tmp_path / "good.toml"
    _pose_file(cap, good, names=cap.take_names()[:2])
    text = good.read_text().replace('name = "v01_000"', 'name = "v99_000"')
    text = text.replace("R = [[", "R = [[2.0, 0, 0], [", 1).replace("t = [", "t = [1.0, ", 1)
    bad = tmp_path / "bad.toml"
    bad.write_text(text + "\n[[views]]\nname = \"v02_000\"\nK = [[0, 0, 1], [0, 1, 1], [0, 0, 1]]\nR = [[1, 0, 0], "
                   "[0, 1, 0], [0, 0, 1]]\nt = [0, 0, 1]\nzoom = 2\n")
    run = CliRunner().invoke(main, ["poses", str(cap.root), "--from", str(bad)])
    assert run.exit_code == 2
    lines = run.output.strip().splitlines()
    print(run.output)
    assert "5 bad field(s)" in lines[0]
    for expected in ("views[0] (v00_000).R: expected 3x3 finite numbers", "views[0] (v00_000).t: expected 3 finite",
                     "views[1].name: 'v99_000' is not an image of this capture",
                     "views[2] (v02_000).zoom: unknown field", "views[2] (v02_000).K: expected [[fx, s, cx]"):
        assert any(expected in line for line in lines[1:]), expected
    assert len(lines) == 6
    run = CliRunner().invoke(main, ["poses", str(cap.root), "--from", str(tmp_path / "nope.toml")])
    assert run.exit_code == 2 and "nope.toml: no such poses file" in run.output
