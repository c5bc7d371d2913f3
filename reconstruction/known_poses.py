"""Known cameras (a calibrated rig, a robot-held camera) as the poses: per-view K, R and t read from a TOML or JSON
file instead of estimated (`PoseSettings.from_file`)."""
from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.contract import plain
from odsplat.spine.errors import InputError
from odsplat.spine.geometry import camera_center_m, rotation_angle_deg
from odsplat.spine.manifest import load_json, load_toml
from odsplat.spine.store import Capture
from odsplat.spine.tags import detect_tags

from .pose_images import Intrinsics, collect_images
from .pose_result import PoseResult, PoseSettings
from .pose_tags import tag_poses, view_pose

_FILE_KEYS = {"name", "K", "R", "t", "dist"}


def poses_from_file(capture: Capture, path: str | Path, settings: PoseSettings | None = None) -> PoseResult:
    """Known cameras (a calibrated rig, a robot-held camera) as the poses: a TOML or JSON file of `[[views]]`, each
    with `name` (a take, or "static/STEM" for a photo), `K` (3x3 px, pixel (0, 0) centred at (0, 0)), `R` (3x3) and
    `t` (3, metres), world to camera (X_cam = R X_world + t, OpenCV axes), and optionally `dist` (OpenCV's 4, 5 or 8
    coefficients). Every bad field is named on its own line of one InputError. Images the file does not name are
    listed as not posed; where a view sees floor tags, its tag pose is compared with the file's (tag_rot_deg)."""
    settings = settings or PoseSettings()
    path = Path(path)
    started = time.perf_counter()
    if path.suffix.lower() == ".toml":
        doc = load_toml(path, missing="no such poses file")
    elif path.suffix.lower() == ".json":
        doc = load_json(path, missing="no such poses file")
    else:
        raise InputError(path, "expected a .toml or .json file of per-view K, R, t")
    images, notes = collect_images(capture, settings)
    by_name = {im.name: im for im in images}
    entries = doc.get("views") if isinstance(doc, dict) else None
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "expected a non-empty list `views` ([[views]] in TOML), each with name, K, R, t")
    problems: list[str] = []
    parsed: dict[str, tuple[Intrinsics, np.ndarray, np.ndarray]] = {}
    for i, entry in enumerate(entries):
        where = f"views[{i}]"
        if not isinstance(entry, dict):
            problems.append(f"{where}: expected a table with name, K, R, t")
            continue
        name = entry.get("name")
        if not isinstance(name, str) or name not in by_name:
            problems.append(f"{where}.name: {name!r} is not an image of this capture (expected a take name or "
                            f"static/STEM, e.g. {images[0].name!r})" if images else f"{where}.name: no images")
        elif name in parsed:
            problems.append(f"{where}.name: {name!r} is given twice")
        where = f"{where} ({name})" if isinstance(name, str) else where
        for key in sorted(set(entry) - _FILE_KEYS):
            problems.append(f"{where}.{key}: unknown field; expected {sorted(_FILE_KEYS)}")
        K = _file_array(entry, "K", (3, 3), where, problems)
        R = _file_array(entry, "R", (3, 3), where, problems)
        t = _file_array(entry, "t", (3,), where, problems)
        dist = np.asarray(entry.get("dist", []), dtype=object).ravel()
        try:
            dist = dist.astype(np.float64)
            if dist.size not in (0, 4, 5, 8) or not np.all(np.isfinite(dist)):
                raise ValueError
        except (TypeError, ValueError):
            problems.append(f"{where}.dist: expected 0, 4, 5 or 8 finite OpenCV coefficients, got "
                            f"{entry.get('dist')!r}")
            dist = None
        if K is not None and (K[0, 0] <= 0 or K[1, 1] <= 0 or K[1, 0] != 0 or np.any(K[2] != [0, 0, 1])):
            problems.append(f"{where}.K: expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
            K = None
        if R is not None and (not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0):
            problems.append(f"{where}.R: not a rotation (R R^T = I within 1e-6 and det +1 expected)")
            R = None
        if all(x is not None for x in (K, R, t, dist)) and name in by_name and name not in parsed:
            parsed[name] = (Intrinsics(K, tuple(float(d) for d in dist)), R, t)
    if problems:
        raise InputError(path, f"{len(problems)} bad field(s):\n  " + "\n  ".join(problems))
    layout = capture.manifest.tags
    views, unposed = [], {}
    for im in images:
        if im.name not in parsed:
            unposed[im.name] = f"not in {path.name}"
            continue
        cam, R, t = parsed[im.name]
        tp = None
        if layout is not None:
            tp = tag_poses([im], {im.name: detect_tags(im.gray, family=layout.family)}, layout, {im.group: cam},
                           settings.min_tags).get(im.name)
        view = view_pose(im, "file", cam, R, t, None, tp)
        if tp is not None:  # a file's pose against the tags: a check of the file
            view.tag_rot_deg = rotation_angle_deg(tp.R, R)
            view.tag_trans_mm = 1e3 * float(np.linalg.norm(camera_center_m(tp.R, tp.t) - camera_center_m(R, t)))
        views.append(view)
    result = PoseResult(views=views, points_m=np.zeros((0, 3)), points_color=np.zeros((0, 1), np.float32),
                        points_error_px=np.zeros(0, np.float32), method="file", sim3_scale=None, sim3_R=None,
                        sim3_t=None, sim3_residual_m=None, registered=0, n_images=len(images),
                        notes=notes + ["no points: the poses were read, not estimated"],
                        reason=f"known cameras from {path}", unposed=unposed, source=str(path))
    result.timings_s = {"total_s": round(time.perf_counter() - started, 3)}
    result.settings = plain(settings)
    return result


def _file_array(entry: Mapping[str, Any], key: str, shape: tuple[int, ...], where: str,
                problems: list[str]) -> np.ndarray | None:
    if key not in entry:
        problems.append(f"{where}.{key}: missing")
        return None
    try:
        a = np.array(entry[key], dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.all(np.isfinite(a)):
        want = "x".join(map(str, shape))
        problems.append(f"{where}.{key}: expected {want} finite numbers, got {entry[key]!r}")
        return None
    return a
