"""The same capture gives the same numbers: a second `odsplat run` of the session's piped capture, into a folder of its
own and on another number of torch threads, reproduces the poses bit for bit and every figure of the first to 6
significant digits (issue 43)."""
from __future__ import annotations

import json
import math

import numpy as np
from click.testing import CliRunner

from odsplat.analysis import read_results_h5
from odsplat.app.cli import main
from odsplat.spine.store import Capture
from tests.conftest import piped_copy

# What legitimately differs between two runs: when and how long, and the run's own identity.
VARIABLE_KEYS = {"created_utc", "run_id", "seconds", "seconds_t0", "seconds_dynamic", "timings_s", "fingerprint",
                 "elapsed_s", "started_utc", "finished_utc"}
DIGITS = 6


def _numbers(value, path: str = ""):
    """Every number in a JSON document, with its path; timings and run identities left out."""
    if isinstance(value, dict):
        for k, v in value.items():
            if k not in VARIABLE_KEYS:
                yield from _numbers(v, f"{path}/{k}")
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _numbers(v, f"{path}[{i}]")
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        yield path, float(value)


def _same(a: float, b: float, scale: float) -> bool:
    """Equal to DIGITS significant digits of the larger of the two or of the quantity's own scale."""
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= 0.5 * 10 ** (1 - DIGITS) * max(abs(a), abs(b), scale * 1e-3)


def test_two_runs_of_one_capture_agree_to_six_significant_digits(piped_original, tmp_path):
    cap_dir = piped_copy(piped_original, tmp_path / "cap")
    second = tmp_path / "second"
    r = CliRunner().invoke(main, ["run", str(cap_dir), "--derived", str(second), "--set", "reconstruct.threads=1"])
    assert r.exit_code == 0, r.output
    first_cap, second_cap = Capture.open(cap_dir), Capture.open(cap_dir, derived=second)
    # the poses bit for bit (COLMAP on one thread)
    pa, pb = (json.loads(c.paths.poses_json.read_text()) for c in (first_cap, second_cap))
    assert [(v["R"], v["t"]) for v in pa["views"]] == [(v["R"], v["t"]) for v in pb["views"]]
    a = json.loads(first_cap.paths.analysis_json.read_text())
    b = json.loads(second_cap.paths.analysis_json.read_text())
    na, nb = dict(_numbers(a)), dict(_numbers(b))
    assert len(na) > 100
    assert na.keys() == nb.keys()
    differ = [(k, na[k], nb[k]) for k in na if not _same(na[k], nb[k], 0.0)]
    assert not differ, differ[:10]
    # The shapes themselves, every point and component: each to 6 digits of the shape's own largest value.
    ra = read_results_h5(first_cap.paths.analysis_dir / "results.h5")
    rb = read_results_h5(second_cap.paths.analysis_dir / "results.h5")
    shapes_b = {s.name: s for s in rb.shapes}
    assert len(ra.shapes) >= 4
    assert {s.name for s in ra.shapes} == set(shapes_b)
    for s in ra.shapes:
        va, vb = np.asarray(s.values), np.asarray(shapes_b[s.name].values)
        scale = float(np.abs(va).max())
        assert np.all(np.abs(va - vb) <= 0.5 * 10 ** (1 - DIGITS) * scale), s.name
        assert s.freq_hz == shapes_b[s.name].freq_hz
