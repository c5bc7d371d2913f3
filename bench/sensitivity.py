"""How sensitive the pipeline's numbers are to a perturbation far below any measurement's: the poses moved by `--eps`
(default 1e-10 m on every camera's translation, the size two machines' floating point may differ by), then the
reconstruction and the analysis run again, against a plain rerun of the same steps on the same poses (the baseline:
equal to the last digit on one machine, tests/test_reproducible.py).

CAPTURE must have been through `odsplat run` (its derived/ is read, never written: each run goes to a copy of it).
Figures per video mode: the MAC at the sensors, the modal scale factor and the largest change of its shape at any point
(relative to the shape's largest value) in each run, and how far apart they are; beside them the MAC the video's noise
allows (`expected_mac`) and whether the mode stands above the noise floor. A mode above its floor whose figures move by
more than its noise allows is a step that amplifies rounding (docs/fidelity.md says which and by how much).

One JSON line on stdout; progress on stderr.
"""
from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.analysis import read_analysis, read_results_h5  # noqa: E402
from odsplat.spine.store import Capture  # noqa: E402


def rerun(capture: Path, derived: Path, log: Path) -> float:
    t0 = time.perf_counter()
    with open(log, "a") as out:
        r = subprocess.run([sys.executable, "-m", "odsplat", "run", str(capture), "--derived", str(derived),
                            "--from", "reconstruct", "--to", "analyze"], stdout=out, stderr=subprocess.STDOUT)
    if r.returncode:
        raise SystemExit(f"odsplat run failed ({r.returncode}): see {log}")
    return time.perf_counter() - t0


def perturb_poses(derived: Path, eps_m: float, seed: int = 1) -> None:
    """Every view's translation moved by eps_m (normal, per axis) in derived/poses.json, written back in place."""
    path = derived / "poses.json"
    doc = json.loads(path.read_text())
    rng = np.random.default_rng(seed)
    for view in doc["views"]:
        view["t"] = (np.asarray(view["t"], float) + eps_m * rng.standard_normal(3)).tolist()
    path.write_text(json.dumps(doc, indent=1))


def figures(capture: Path, derived: Path) -> dict[int, dict]:
    cap = Capture.open(capture, derived=derived)
    doc = read_analysis(cap)
    res = read_results_h5(cap.paths.analysis_dir / "results.h5", capture_id=cap.id)
    shapes = {s.number: np.asarray(s.values) for s in res.shapes if s.shape_set == "video" and s.kind == "mode"}
    floor = {round(e.freq_hz, 3): e for e in (doc.video.noise_floor.modes if doc.video and doc.video.noise_floor
                                              else ())}
    out = {}
    for p in doc.correlation.pairs if doc.correlation else ():
        fl = floor.get(round(doc.modes[p.a].freq_hz, 3))       # pairs count modes from 0, shapes from 1
        out[p.a + 1] = {"freq_hz": doc.modes[p.a].freq_hz, "mac": p.mac, "scale": p.scale_factor_abs,
                    "expected_mac": p.expected_mac, "below_floor": bool(fl.below_floor) if fl else None,
                    "shape": shapes.get(p.b + 1)}
    return out


def compare(a: dict[int, dict], b: dict[int, dict]) -> list[dict]:
    rows = []
    for k in sorted(a):
        x, y = a[k], b.get(k)
        if y is None:
            continue
        sx, sy = x["shape"], y["shape"]
        shape = (float(np.abs(sx - sy).max() / max(np.abs(sx).max(), 1e-300))
                 if sx is not None and sy is not None and sx.shape == sy.shape else None)
        rows.append({"mode": k, "freq_hz": x["freq_hz"], "below_floor": x["below_floor"],
                     "expected_mac": x["expected_mac"], "mac": [x["mac"], y["mac"]],
                     "mac_change": abs(x["mac"] - y["mac"]), "scale": [x["scale"], y["scale"]],
                     "scale_change_rel": abs(x["scale"] - y["scale"]) / max(abs(x["scale"]), 1e-300),
                     "shape_change_rel": shape})
    return rows


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("capture", type=Path)
    ap.add_argument("--eps", type=float, default=1e-10, help="the poses' perturbation, metres")
    a = ap.parse_args(argv)
    src = Capture.open(a.capture).derived_dir
    with tempfile.TemporaryDirectory(prefix="odsplat-sensitivity-") as tmp:
        base, plain, moved = (Path(tmp) / n for n in ("base", "plain", "moved"))
        for d in (plain, moved):
            shutil.copytree(src, d, symlinks=True)
        perturb_poses(moved, a.eps)
        log = Path(tmp) / "run.log"
        seconds = [rerun(a.capture, plain, log), rerun(a.capture, moved, log)]
        shutil.copytree(src, base, symlinks=True)
        f0, f1, f2 = figures(a.capture, base), figures(a.capture, plain), figures(a.capture, moved)
    rows_plain, rows_moved = compare(f0, f1), compare(f0, f2)
    above = [r for r in rows_moved if r["below_floor"] is False]
    out = {"bench": "sensitivity", "capture": str(a.capture), "eps_m": a.eps, "seconds": seconds,
           "rerun": rows_plain, "perturbed": rows_moved,
           "rerun_max_shape_change": max((r["shape_change_rel"] or 0.0 for r in rows_plain), default=None),
           "perturbed_max_shape_change_above_floor": max((r["shape_change_rel"] or 0.0 for r in above), default=None),
           "perturbed_max_mac_change_above_floor": max((r["mac_change"] for r in above), default=None)}
    print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
