"""The spread of a bench's figures over seeds: every number's worst and median, and the targets judged on the worst."""
from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

HIGHER_IS_BETTER = ("mac", "found", "psnr", "ssim", "r2", "n_identified", "snr", "registered", "n_points",
                    "n_averages", "correlation")
NEAR_ONE = ("scale_factor", "gain", "amplitude", "rms_ratio")


def _leaves(x, path: str = "") -> dict[str, object]:
    """Flat {dotted path: value} of a figures dict's numbers and booleans (lists by index)."""
    out: dict[str, object] = {}
    if isinstance(x, dict):
        for k, v in x.items():
            out.update(_leaves(v, f"{path}.{k}" if path else str(k)))
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            out.update(_leaves(v, f"{path}[{i}]"))
    elif isinstance(x, (bool, np.bool_)):
        out[path] = bool(x)
    elif isinstance(x, (int, float, np.integer, np.floating)) and np.isfinite(x):
        out[path] = float(x)
    return out


def _worst(key: str, values: list[float]) -> float:
    name = key.rsplit(".", 1)[-1].lower()
    v = np.asarray(values, float)
    if any(w in name for w in NEAR_ONE):
        return float(v[np.argmax(np.abs(v - 1))])
    if any(w in name for w in HIGHER_IS_BETTER):
        return float(v.min())
    return float(v[np.argmax(np.abs(v))])          # errors, seconds, counts of misses: the largest


def spread(runs: list[dict], skip: tuple[str, ...] = ("settings", "true_hz", "true_damping", "true_peak_um",
                                                     "truth_peak")
           ) -> dict[str, dict]:
    """{path: {"worst", "median", "n"}} for every number present in at least one run (booleans: worst is False
    if any run is False); paths under `skip` are left out (the settings, the truth's own values)."""
    leaves = [_leaves(r) for r in runs]
    keys = sorted({k for lv in leaves for k in lv})
    out: dict[str, dict] = {}
    for k in keys:
        if any(part in k.replace("[", ".").split(".") for part in skip):
            continue
        vals = [lv[k] for lv in leaves if k in lv]
        if all(isinstance(v, bool) for v in vals):
            out[k] = {"worst": all(vals), "median": None, "n": len(vals)}
        else:
            nums = [float(v) for v in vals]
            out[k] = {"worst": _worst(k, nums), "median": float(np.median(nums)), "n": len(nums)}
    return out


def targets_on_worst(runs: list[dict]) -> dict[str, bool | None]:
    """Each target met only if met on every seed (None where no seed judged it)."""
    names = sorted({k for r in runs for k in (r.get("targets") or {})})
    out: dict[str, bool | None] = {}
    for n in names:
        vals = [(r.get("targets") or {}).get(n) for r in runs]
        judged = [v for v in vals if v is not None]
        out[n] = all(judged) if judged else None
    return out


def run_seeds(args: argparse.Namespace, seeds: list[int], run_seed: Callable[[argparse.Namespace, Path], dict],
              prefix: str) -> list[dict]:
    """Each seed's figures, its capture in --keep (one seed) or a folder per seed (in --keep, else a temporary
    one)."""
    tmp = tempfile.TemporaryDirectory(prefix=prefix)
    runs = []
    for seed in seeds:
        print(f"seed {seed}", file=sys.stderr)
        if args.keep is not None and len(seeds) == 1:
            where = args.keep
        else:
            where = (args.keep or Path(tmp.name)) / (f"seed{seed}" if len(seeds) > 1 else "cap")
        runs.append(run_seed(argparse.Namespace(**{**vars(args), "seed": seed}), where))
    tmp.cleanup()
    return runs
