"""bench/fidelity.py's scoring, on small data: the truth it scores against, the points it scores, and its figures on
the session's piped capture (the bench itself runs `odsplat run` on four structures: minutes, docs/fidelity.md)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.analysis import receptance
from odsplat.hil_sim.structure import make_structure
from odsplat.spine.store import Capture


@pytest.mark.parametrize("name", ["arm", "plate", "frame", "mast"])
def test_true_residues_give_the_structures_own_frf(name, bench_script):
    """The residues the video is scored against sum, as the analysis sums its own (ods.receptance), to the
    structure's analytic receptance: the convention (m/N, phi phi / (2 i w_d)) is the analysis', scale included."""
    fid = bench_script("fidelity")
    st = make_structure(name)
    lo, hi = next(iter(st.geometry.boxes().values())) if name != "frame" else list(st.geometry.boxes().values())[-1]
    point = np.array([[hi[0], 0.5 * (lo[1] + hi[1]), hi[2]]])                      # a corner of a moving part
    hammer, d = point[0], np.array([0.6, 0.0, -0.8])
    res = fid.true_residues(st, point, hammer, d, st.freqs_hz)[:, 0]                # (R, 3)
    poles = np.array([-m.damping * m.omega + 1j * m.omega * np.sqrt(1 - m.damping ** 2) for m in st.modes])
    f = np.array([0.5, 1.0, 1.3]) * st.freqs_hz[0]
    ours = receptance(res, poles, f) @ d                                            # (F,) along d at the point
    exact = st.frf(point[0], d, hammer, d, f)
    assert np.allclose(ours, exact, rtol=1e-6, atol=1e-12 * np.abs(exact).max())


def test_points_snap_to_the_structure_surface_and_floaters_do_not(bench_script):
    fid = bench_script("fidelity")
    st = make_structure("arm")
    lo, hi = st.geometry.boxes()["column"]
    face = np.array([hi[0], 0.0, 0.4])                                              # on the column's +x face
    pts = np.array([face + [0.01, 0, 0], face - [0.005, 0, 0], [0.0, 0.6, 0.3]])     # outside, inside, in the air
    near, on = fid.snap(st, pts)
    assert on.tolist() == [True, True, False]
    assert np.allclose(near[:2], face, atol=1e-12)


def test_scores_every_true_mode_of_a_piped_capture(piped_original, bench_script):
    """Every true mode gets a row; the fitted ones a full-field MAC, scale and field error from the real results.h5
    and analysis.json; the analysis' own judgement comes along."""
    fid = bench_script("fidelity")
    cap = Capture.open(piped_original)
    st = make_structure("arm")
    out = fid.score_modes(cap, st)
    assert [m["mode"] for m in out["modes"]] == list(range(1, st.n_modes + 1))
    fitted = [m for m in out["modes"] if m["fitted"]]
    assert fitted and out["verdict"] is not None
    for m in fitted:
        assert m["n_points"] > 0 and m["status"] is not None and m["below_floor"] is not None
        if "mac_full" in m:
            assert 0.0 <= m["mac_full"] <= 1.0 + 1e-12 and m["scale"] >= 0 and m["field_rel_err"] >= 0
    assert fid.targets([{"case": "piped", **out}], None)["below_floor_never_met"]


def test_targets_judge_every_mode_above_the_floor_and_keep_the_tuned_rig_apart(bench_script):
    """A wrong mode above the floor fails the target wherever it is; the issue's goal (new structures) ignores the
    arm the defaults were tuned on, and a mode flagged below the floor or not separated is never judged."""
    fid = bench_script("fidelity")
    good = {"fitted": True, "below_floor": False, "status": "met", "mac_full": 0.97, "scale": 1.05,
            "found_within_1pct": True, "mode": 1, "true_hz": 59.4}
    wrong = {**good, "mode": 2, "true_hz": 262.0, "mac_full": 0.93, "status": "not discriminated"}
    flagged = {**wrong, "mode": 3, "below_floor": True, "status": "below floor"}
    apart = {**wrong, "mode": 4, "status": "not separated"}
    rows = [{"case": "plate", "structure": "plate", "modes": [good, flagged, apart]},
            {"case": "arm", "structure": "arm", "modes": [good, wrong]}]
    t = fid.targets(rows, None)
    assert t["n_judged"] == 3 and t["wrong"] == ["arm mode 2 (262.0 Hz)"]
    assert not t["modes_above_floor_right"] and t["new_structures_modes_right"]
    rows[0]["modes"].append({**wrong, "mode": 5})
    t = fid.targets(rows, None)
    assert not t["new_structures_modes_right"] and "plate mode 5 (262.0 Hz)" in t["wrong"]
