"""One view with a hammer and accelerometers (issue 45): the hil_sim arm filmed from one viewpoint on the side, where
the column's x sensor and the tip's z sensor lie in the image plane, goes `odsplat run`; the analysis poses the view
from the tags in its first frame, reads the two sensors in the 2D tracks around them and compares each mode's
residues with the accelerometers'."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from odsplat.acquisition.plan import PlanSettings
from odsplat.analysis.sensorview import view_pose
from odsplat.hil_sim.bench import simulate_capture
from odsplat.hil_sim.video import VideoSimSettings, simulate_video
from odsplat.spine.store import Capture

# one view from the +y side, 10 degrees up, 1 m from the arm: 430-440 px/m at the sensors
SIDE = PlanSettings(n_views=1, radius_m=1.0, target_m=(0.2, 0.0, 0.42), elevation_deg=(5.0, 15.0),
                    azimuth_offset_deg=90.0)


@pytest.fixture(scope="module")
def side_capture(tmp_path_factory):
    cap = tmp_path_factory.mktemp("one-view") / "cap"
    simulate_capture(cap, n_frames=300, record_s=0.5, plan=SIDE)
    run = subprocess.run([sys.executable, "-m", "odsplat", "run", str(cap)], capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stdout + run.stderr
    return cap, run.stdout


def test_the_view_is_posed_from_its_tags(side_capture):
    cap, _ = side_capture
    capture = Capture.open(cap)
    K, R, t, source = view_pose(capture, "v00_000", at_rest=True)
    centre = -R.T @ t
    # the session placed the camera at 1 m from the target, 10 degrees up, on +y
    assert "tags" in source
    assert np.linalg.norm(centre - [0.2, 0.0, 0.42]) == pytest.approx(1.0, abs=0.03)
    assert np.degrees(np.arctan2(centre[1], centre[0] - 0.2)) == pytest.approx(90.0, abs=2.0)


def test_the_sensors_in_the_image_plane_agree_with_the_video(side_capture):
    cap, stdout = side_capture
    doc = json.loads((cap / "derived" / "analysis" / "analysis.json").read_text())
    sv = doc["sensor_view"]
    assert [s["name"] for s in sv["sensors"]] == ["acc_tip_z", "acc_col_x"]
    # the y sensors' axes point along the line of sight: left out, with why
    assert {s["name"] for s in sv["left_out"]} == {"acc_tip_y", "acc_col_y"}
    assert all("out of the image plane" in s["why"] for s in sv["left_out"])
    modes = {m["mode"]: m for m in sv["modes"]}
    # the arm's in-plane bending modes (23.5, 86, 262 Hz): judged, shapes and scale as the accelerometers'
    for k in (1, 3, 5):
        assert modes[k]["judged"], modes[k]
        assert modes[k]["mac"] >= 0.99, modes[k]
        assert 0.8 <= modes[k]["scale"] <= 1.2, modes[k]
        assert abs(modes[k]["scale_phase_deg"]) < 10, modes[k]
    # the y bending (31 Hz) hardly moves these two sensors: not judged, and said so
    assert not modes[2]["judged"] and modes[2]["seen_share"] < 0.3
    assert "one view against the accelerometers" in stdout
    html = (cap / "derived" / "analysis" / "report.html").read_text()
    assert "One view against the accelerometers" in html and "acc_col_x" in html
    assert "One view against its accelerometers (2 in the image plane): mode 1 (23.5 Hz) MAC" in html   # the summary


# ------------------------------------------------------------------------------------------ without force

@pytest.fixture(scope="module")
def unforced_capture(tmp_path_factory):
    """The arm hit once by nobody's hammer, filmed from the same side (320x240 px, 1000 fps, 512 frames), its four
    accelerometers recorded on the camera's clock; no force channel."""
    folder = tmp_path_factory.mktemp("one-view-no-force")
    rig = simulate_video(folder / "sim", VideoSimSettings(
        structure="arm", accelerometers=True, excitation="hit", peak_n=1500.0, width_px=320, height_px=240,
        fov_deg=40.0, eye_m=(0.22, 1.2, 0.5), target_m=(0.22, 0.0, 0.36), n_frames=512, fps=1000.0))
    cap = folder / "cap"
    for args in (["import", str(rig), "-o", str(cap)], ["run", str(cap), "--set", "analyze.video2d.clips=false",
                                                     "--set", "analyze.video2d.max_points=100"]):
        run = subprocess.run([sys.executable, "-m", "odsplat", *args], capture_output=True, text=True, timeout=900)
        assert run.returncode == 0, run.stdout + run.stderr
    return cap, run.stdout


def test_without_force_the_sensors_in_the_image_plane_agree_with_the_video(unforced_capture):
    cap, stdout = unforced_capture
    sync = json.loads((cap / "derived" / "sync.json").read_text())["takes"][0]
    assert "no_force" in sync["flags"] and "daq_clock" in sync["flags"]      # the DAQ's samples on the frames' time
    doc = json.loads((cap / "derived" / "analysis" / "video2d.json").read_text())
    sv = doc["sensor_view"]
    assert sv["method"] == "ods" and [s["name"] for s in sv["sensors"]] == ["acc_tip_z", "acc_col_x"]
    by_hz = {round(m["freq_hz"]): m for m in sv["modes"]}
    # the in-plane bending modes (the 23.5 Hz one a free decay, no harmonic): shape and scale as the accelerometers'
    for f in (24, 86, 262):
        m = by_hz[f]
        assert m["judged"] and m["mac"] >= 0.99 and abs(m["scale"] - 1) <= 0.1, m
    assert not by_hz[31]["judged"] and by_hz[31]["seen_share"] < 0.3                # the y bending: out of view
    assert all(s["r2"] > 0.5 for s in sv["sensors"])          # each reading coheres with its accelerometer
    assert "one view against the accelerometers" in stdout
    html = (cap / "derived" / "analysis" / "report.html").read_text()
    assert "One view against the accelerometers" in html and "one FDD of the readings" in html
    assert "One view against its accelerometers (2 in the image plane): mode 1 (23.5 Hz) MAC" in html   # the setup
