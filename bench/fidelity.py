"""Fidelity beyond the arm: `odsplat run` with the defaults on each of hil_sim's structures, every mode scored against
the structure's own modal truth over the whole visible surface, not only at the accelerometers.

Each case records a guided capture with `odsplat capture --sim --auto` (its structure, texture, image size, frame rate,
bit depth, views and floor-tag size vary from case to case, docs/fidelity.md) and runs `odsplat run` on it with no
settings file: what a user gets. Then, per true mode in the camera's band:
- `found_hz`: the video's own pole nearest the true frequency (matrix pencil on the raw frames' most textured pixels
  and on the reconstruction's motion, no accelerometer), and whether it lies within 1 %;
- the full-field shape: the video's residues (m/N, results.h5 "video mode K") at every surface point the analysis
  kept on the structure, against the true residue there, phi_r(p) (phi_r(hammer) . d) / (2 i w_d) for the
  mass-normalised shapes (the point moved to the nearest point of the structure's surface, within SNAP_M; points
  farther off are counted, not scored): MAC over all three components (`mac_full`), the modal scale factor's modulus
  and phase (`scale`, `phase_deg`: 1 and 0 are exact) and the relative error of the displacement field
  (`field_rel_err`, ||video - truth|| / ||truth||);
- the analysis' own view of the mode: above or below the video's noise floor, its status in the verdict, and the MAC at
  the sensors (what the analysis could judge without the truth).
Baseline in the same run: the MAC at the sensors of the same video shapes (what the analysis reports), against the
full field's. `motion` (the motion-only metric of bench/reconstruct.py) renders the trained model at two views'
estimated poses, magnified, against hil_sim's noise-free renders from the true cameras with the motion magnified
alike: each less its rest image, PSNR against the truth motion's peak, and their correlation.

Targets (last line, `targets`): on every structure, every mode above the floor reads mac_full >= 0.95, scale within
10 % and its frequency found by the video within 1 %; no mode below the floor or undiscriminated is called met.
`--demo CAPTURE` also scores the motion metric on an existing capture (the demo's, `make demo`): >= 20 dB.

One JSON line per case, then the summary line, on stdout; progress on stderr.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from reconstruct import GroundTruth, box, motion_scores  # noqa: E402

from odsplat.analysis import read_analysis, read_results_h5  # noqa: E402
from odsplat.analysis.correlation import mac, modal_scale_factor  # noqa: E402
from odsplat.hil_sim.camera import SimCameraConfig  # noqa: E402
from odsplat.hil_sim.rig import TakeTruth, make_rig, truth_path  # noqa: E402
from odsplat.hil_sim.scene import SceneSettings  # noqa: E402
from odsplat.reconstruction.model import DynamicScene, pose_camera  # noqa: E402
from odsplat.reconstruction.pose_result import PoseResult  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402

log = logging.getLogger("bench.fidelity")

SNAP_M = 0.025           # a surface point farther than this from the structure's surface is not on it: the
#                          Gaussians sit 4-15 mm off it (quartiles, arm at 320x240, 128 px training width)
SURFACE_NODE0 = 1001     # analysis/outputs.py: the video's surface points are numbered from here
MIN_MAC, MAX_SCALE_ERR, MAX_FREQ_ERR = 0.95, 0.10, 0.01
TUNED_ON = "arm"         # the structure the defaults were tuned on (the demo's): not one of the new ones


@dataclass(frozen=True)
class Case:
    """One structure and the rig around it: `odsplat capture --sim` options."""

    name: str
    structure: str
    texture: str = "speckle"
    size: str = "320x240"
    fps: float = 2000.0
    bit_depth: int = 12
    views: int = 12
    floor_tag_m: float = 0.12
    record_s: float = 0.128      # frames = record_s x fps
    hammer_force_n: float = 200.0   # the automatic hammer's set force (capture's default)

    @property
    def frames(self) -> int:
        return int(round(self.record_s * self.fps))

    def capture_args(self) -> list[str]:
        return ["--structure", self.structure, "--texture", self.texture, "--size", self.size,
                "--fps", f"{self.fps:g}", "--bit-depth", str(self.bit_depth), "--views", str(self.views),
                "--floor-tag-m", f"{self.floor_tag_m:g}", "--frames", str(self.frames), "--pretrigger-frames", "10",
                "--hammer-force-n", f"{self.hammer_force_n:g}"]


CASES = {
    "arm": Case("arm", "arm", views=12),
    "plate": Case("plate", "plate", texture="value_noise", fps=1000.0, bit_depth=8, views=9, floor_tag_m=0.10),
    # The plate hit three times harder, filmed from 8 views: every mode rises above the sensors' floor, and the
    # floor over the whole plate must flag its (3,1) and (3,2) modes (docs/fidelity.md). It was the suite's plate
    # test (tests/test_fidelity.py) until the suite passed its 15 minutes: 2-4 minutes on two cores.
    "plate_600n": Case("plate_600n", "plate", texture="value_noise", fps=1000.0, bit_depth=8, views=8,
                       hammer_force_n=600.0),
    "frame": Case("frame", "frame", size="256x256", views=12),
    # The same frame as a test engineer would film it once the above says its members are too thin: twice the
    # pixels across them and a three times harder hit (not in the default set: about 4x the frame's time).
    "frame_fine": Case("frame_fine", "frame", size="512x512", views=12, hammer_force_n=600.0),
    "mast": Case("mast", "mast", texture="checker", size="400x300", fps=2500.0, views=12, floor_tag_m=0.14,
                 record_s=0.1),
}
DEFAULT_CASES = ("arm", "plate", "frame", "mast")


def odsplat(*args: str, log_path: Path, ok: tuple[int, ...] = (0,)) -> tuple[float, int]:
    """Run the odsplat command as a user would; its output goes to log_path. Returns the seconds it took and its
    status (one of `ok`, else the bench stops)."""
    t0 = time.perf_counter()
    with open(log_path, "a") as out:
        r = subprocess.run([sys.executable, "-m", "odsplat", *args], stdout=out, stderr=subprocess.STDOUT)
    if r.returncode not in ok:
        raise SystemExit(f"odsplat {' '.join(args)} failed with status {r.returncode}: see {log_path}")
    return time.perf_counter() - t0, r.returncode


def true_residues(structure, points_m: np.ndarray, hammer_m, hammer_dir, freqs_hz) -> np.ndarray:
    """(R, P, 3) the displacement residues (m/N) of the structure's modes at points for a unit force at the hammer:
    phi_r(p) (phi_r(hammer) . d) / (2 i w_d), the convention of analysis.ods.receptance."""
    phi = structure.mode_shapes(points_m)                                          # (P, R, 3)
    gamma = structure.participation(hammer_m, hammer_dir)                          # (R,)
    out = []
    for k, m in enumerate(structure.modes):
        wd = 2 * np.pi * m.freq_hz * np.sqrt(1 - m.damping ** 2)
        out.append(phi[:, k] * gamma[k] / (2j * wd))
    return np.array(out)


def snap(structure, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each point moved to the nearest point of the structure's surface (the union of its boxes, `geometry.boxes()`),
    and a mask of the points within SNAP_M of it (a Gaussian sits on the surface to about its own size)."""
    p = np.asarray(points_m, float).reshape(-1, 3)
    best = np.full(len(p), np.inf)
    near = p.copy()
    for lo, hi in structure.geometry.boxes().values():
        q = np.clip(p, lo, hi)
        inside = np.all((p >= lo) & (p <= hi), axis=1)
        if inside.any():                       # inside: out through the nearest face
            d_lo, d_hi = p[inside] - lo, hi - p[inside]
            d = np.concatenate([d_lo, d_hi], axis=1)
            k = np.argmin(d, axis=1)
            qi = p[inside].copy()
            axis = k % 3
            qi[np.arange(len(qi)), axis] = np.where(k < 3, lo[axis], hi[axis])
            q[inside] = qi
        dist = np.linalg.norm(p - q, axis=1)
        better = dist < best
        best[better], near[better] = dist[better], q[better]
    return near, best <= SNAP_M


def score_modes(cap: Capture, structure) -> dict:
    """Every true mode in the band: found by the video, its full-field MAC, scale and field error, and the analysis'
    own judgement of it."""
    doc = read_analysis(cap)
    res = read_results_h5(cap.paths.analysis_dir / "results.h5", capture_id=cap.id)
    hammer = next(c for c in cap.manifest.channels if c.name == "force")
    nodes = {int(i): np.asarray(c, float) for i, c in zip(res.geometry.node_ids, res.geometry.coords_m)}
    video = {s.number: s for s in res.shapes if s.shape_set == "video" and s.kind == "mode"}
    acc_f = np.array([m.freq_hz for m in doc.modes])
    f_true = structure.freqs_hz
    v = doc.video
    floor = {round(e.freq_hz, 3): e for e in (v.noise_floor.modes if v and v.noise_floor else ())}
    pairs = {p.a: p for p in (doc.correlation.pairs if doc.correlation else ())}
    statuses = {}
    verdict = doc.correlation.verdict if doc.correlation else None
    for entry in (verdict.modes if verdict else ()):
        statuses[round(float(entry.freq_hz), 3)] = entry.status
    out, off = [], 0
    for r, ft in enumerate(f_true):
        row: dict = {"mode": r + 1, "name": structure.modes[r].name, "true_hz": float(ft)}
        # the video alone: the poles of the raw frames (image poles) and of the reconstruction's motion
        own = np.concatenate([np.asarray(doc.image_poles.freq_hz if doc.image_poles else (), float),
                              np.asarray(v.freq_hz if v else (), float)])
        if own.size:
            k = int(np.argmin(np.abs(own - ft)))
            row["found_hz"] = float(own[k])
            row["found_within_1pct"] = bool(abs(own[k] - ft) <= MAX_FREQ_ERR * ft)
        else:
            row["found_hz"], row["found_within_1pct"] = None, False
        a = int(np.argmin(np.abs(acc_f - ft))) if acc_f.size else -1
        if a < 0 or abs(acc_f[a] - ft) > 0.03 * ft or (a + 1) not in video:
            row["fitted"] = False
            out.append(row)
            continue
        shape = video[a + 1]
        ids = np.asarray(shape.node_ids)
        surf = ids >= SURFACE_NODE0
        pts = np.stack([nodes[int(i)] for i in ids[surf]]) if surf.any() else np.zeros((0, 3))
        on_pts, on = snap(structure, pts) if len(pts) else (pts, np.zeros(0, bool))
        off = int((~on).sum())
        vid = np.asarray(shape.values)[surf][on]                                    # (P, 3) m/N
        tru = true_residues(structure, on_pts[on], hammer.position_m, hammer.direction, f_true)[r]
        key = round(float(acc_f[a]), 3)
        fl = floor.get(key)
        row.update(fitted=True, n_points=int(on.sum()),
                   below_floor=bool(fl.below_floor) if fl else None,
                   status=statuses.get(key), mac_sensors=float(pairs[a].mac) if a in pairs else None)
        if on.sum() >= 3:
            vv, tt = vid.reshape(1, -1), tru.reshape(1, -1)
            msf = complex(np.ravel(modal_scale_factor(vv, tt))[0])
            row.update(mac_full=float(np.ravel(mac(vv, tt))[0]), scale=abs(msf),
                       phase_deg=float(np.degrees(np.angle(msf))),
                       field_rel_err=float(np.linalg.norm(vid - tru) / max(np.linalg.norm(tru), 1e-300)))
        out.append(row)
    return {"modes": out, "n_surface_off_structure": off,
            "verdict": verdict.status if verdict else None, "verdict_line": verdict.line if verdict else None}


def motion_metric(cap: Capture, rig, n_views: int = 2, alpha: float = 30.0, width: int = 160) -> dict | None:
    """The motion-only metric (bench/reconstruct.py `motion_scores`: each render less its render at rest) of the
    trained model on n_views of its takes, rendered at the estimated poses and magnified alpha times, against two
    references: `images`, hil_sim's noise-free renders from the true cameras with the motion magnified alike (the
    issue's metric: it also scores how well the model reproduces the texture, whose gradients turn motion into
    image change), and `same_texture`, the model itself moved by the true motion (each Gaussian on the structure
    by the structure's true displacement where it sits, the others still): the motion alone."""
    scene = DynamicScene.load(cap)
    poses = PoseResult.read(cap)
    names = [t.name for t in cap.manifest.takes if truth_path(cap.takes_dir / f"{t.name}.h5").is_file()]
    names = names[:: max(1, len(names) // n_views)][:n_views]
    near, on = snap(rig.structure, scene.means_rest_m)
    phi = rig.structure.mode_shapes(near) * on[:, None, None]                       # (N, R, 3)
    t0 = float(scene.times_s[0])
    pairs: dict[str, tuple[list, list]] = {"images": ([], []), "same_texture": ([], [])}
    for name in names:
        gt = GroundTruth(rig, TakeTruth.load(truth_path(cap.takes_dir / f"{name}.h5")), width, SimCameraConfig())
        q = np.stack([gt.q(float(t)) for t in scene.times_s])                      # (T, R)
        moved = dataclasses.replace(scene, displacement_m=np.einsum("nrc,tr->tnc", phi, q),
                                    quats=np.repeat(scene.quats[:1], len(scene.times_s), axis=0), basis=None,
                                    shapes_m=None, rot_shapes_rad=None, source_alpha=1.0)
        cam = pose_camera(poses, name, width)
        ref0, mask0 = gt.image(t0, alpha)
        still = scene.render(cam, t0, alpha=alpha)[..., 0]
        still_true = moved.render(cam, t0, alpha=alpha)[..., 0]
        for t in scene.times_s[1:]:
            ref, mask = gt.image(float(t), alpha)
            crop = box(mask0 | mask, 3)
            img = np.asarray(scene.render(cam, float(t), alpha=alpha)[..., 0] - still, float)[crop]
            pairs["images"][0].append(img)
            pairs["images"][1].append(np.asarray(ref[crop], float) - np.asarray(ref0[crop], float))
            pairs["same_texture"][0].append(img)
            pairs["same_texture"][1].append(np.asarray(moved.render(cam, float(t), alpha=alpha)[..., 0] - still_true,
                                                       float)[crop])
    if not names:
        return None
    return {**{k: motion_scores(a, b) for k, (a, b) in pairs.items()}, "views": names, "alpha": alpha,
            "width_px": width}


def run_case(case: Case, root: Path, *, motion_views: int, from_stage: str | None = None) -> dict:
    """Capture (unless the case's capture is there already), run with the defaults (`odsplat run`; from_stage:
    `--from` that stage, to rerun what changed), score."""
    out = root / case.name
    logf = root / f"{case.name}.log"
    fig: dict = {"case": case.name, "structure": case.structure, "texture": case.texture, "size": case.size,
                 "fps": case.fps, "bit_depth": case.bit_depth, "views": case.views, "frames": case.frames,
                 "floor_tag_m": case.floor_tag_m}
    if not (out / "capture.json").is_file():
        # Status 1: the capture is incomplete (views whose takes QC refused every time); the pipeline goes on with
        # the views it has, as the demo does, and the figures say so.
        fig["capture_s"], status = odsplat("capture", str(out), "--sim", "--auto", "--no-window",
                                           *case.capture_args(), log_path=logf, ok=(0, 1))
        fig["capture_complete"] = status == 0
    fig["run_s"], _ = odsplat("run", str(out), *(("--from", from_stage) if from_stage else ()), log_path=logf)
    cap = Capture.open(out)
    fig["views_accepted"] = len({t.view for t in cap.manifest.takes if t.qc == "accepted"})
    rig = make_rig(case.structure, SceneSettings(floor_tag_size_m=case.floor_tag_m, texture=case.texture))
    fig.update(score_modes(cap, rig.structure))
    fig["motion"] = motion_metric(cap, rig, motion_views) if motion_views else None
    return fig


def targets(rows: list[dict], demo: dict | None) -> dict:
    """The issue's goals, judged on every case: each mode above the floor right; none below it called met."""
    bad, new, judged, flagged_ok = [], [], 0, True
    for row in rows:
        for m in row["modes"]:
            if not m.get("fitted"):
                continue
            if m.get("status") in ("below floor", "not discriminated", "not separated"):
                flagged_ok &= m.get("status") != "met"
            if m.get("below_floor") or m.get("status") in ("below floor", "not separated"):
                continue                        # flagged: not judged
            judged += 1                         # every mode above the floor, discriminated or not
            ok = (m.get("mac_full", 0) >= MIN_MAC and abs(m.get("scale", 0) - 1) <= MAX_SCALE_ERR
                  and m.get("found_within_1pct"))
            if not ok:
                bad.append(f"{row['case']} mode {m['mode']} ({m['true_hz']:.1f} Hz)")
                if row.get("structure") != TUNED_ON:   # the goal: the structures the defaults were not
                    new.append(bad[-1])                # tuned to (the arm, the demo's rig, apart)
    out = {"modes_above_floor_right": not bad and judged > 0, "n_judged": judged, "wrong": bad,
           "new_structures_modes_right": not new and judged > 0, "below_floor_never_met": flagged_ok}
    if demo is not None:
        img, own = demo["images"], demo["same_texture"]
        out["demo_motion_db_ge_20"] = bool(img.get("psnr_db") is not None and img["psnr_db"] >= 20)
        # the PSNR alone flatters a model that does not move (still_psnr_db): the motion must also beat that
        out["demo_motion_beats_still"] = bool(img.get("psnr_db") is not None and img["still_psnr_db"] is not None
                                              and img["psnr_db"] > img["still_psnr_db"])
        out["demo_motion_same_texture_db_ge_20"] = bool(own.get("psnr_db") is not None and own["psnr_db"] >= 20)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(DEFAULT_CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--out", type=Path, default=REPO / "bench" / "out" / "fidelity")
    ap.add_argument("--views", type=int, default=None, help="override every case's number of views")
    ap.add_argument("--record-s", type=float, default=None, help="override every case's record length")
    ap.add_argument("--motion-views", type=int, default=2, help="views scored by the motion metric (0: none)")
    ap.add_argument("--demo", type=Path, default=None, help="an existing capture (the demo's) to score the motion of")
    ap.add_argument("--from", dest="from_stage", default=None, help="rerun `odsplat run` from this stage on the "
                    "captures already in --out (e.g. analyze, after a change to the analysis)")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in [c for c in a.cases.split(",") if c]:               # --cases "": the demo's motion alone
        case = CASES[name]
        over = {k: v for k, v in (("views", a.views), ("record_s", a.record_s)) if v is not None}
        case = Case(**{**case.__dict__, **over})
        log.info("%s: %s", name, case)
        row = run_case(case, a.out, motion_views=a.motion_views, from_stage=a.from_stage)
        print(json.dumps(row), flush=True)
        rows.append(row)
    demo = None
    if a.demo is not None:
        cap = Capture.open(a.demo)      # the demo's rig: the arm in hil_sim's own scene (app/demo.py)
        demo = motion_metric(cap, make_rig("arm"), 4)
    summary = {"summary": True, "demo_motion": demo, "targets": targets(rows, demo)}
    print(json.dumps(summary), flush=True)
    return summary


if __name__ == "__main__":
    main()
