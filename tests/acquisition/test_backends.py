"""The camera back ends by name (acquisition/backends.py) and the one set-up function: a lab file's `[camera]
driver = "sim"` runs the simulated rig as `odsplat capture --sim` does, an unknown back end is one line listing the
known ones, and the [camera] keys go to the back end's class. Ground truth: the simulated rig's impacts."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from odsplat.acquisition import BACKENDS, load_lab_config
from odsplat.acquisition.backends import backend
from odsplat.app.cli import main
from odsplat.hil_sim.rig import TakeTruth, truth_path
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture

REPO = Path(__file__).resolve().parents[2]
SMALL = ["--views", "1", "--frames", "12", "--pretrigger-frames", "3", "--record-s", "0.1", "--no-window"]
SIM_LAB = """
[camera]
driver = "sim"
sim = { size_px = [320, 240], seed = 3, faults = "0:double_hit" }

[hammer]
force_n = 150.0
"""


def test_the_table_names_each_back_end_and_acquisition_never_imports_the_simulated_one():
    from odsplat.acquisition.opencv_camera import OpenCVCamera
    from odsplat.acquisition.photron import PhotronCamera
    from odsplat.hil_sim import SimBench

    assert list(BACKENDS) == ["opencv", "photron", "sim"]
    assert (backend("opencv"), backend("photron"), backend("sim")) == (OpenCVCamera, PhotronCamera, SimBench)
    probe = "import sys, odsplat.acquisition; print(sorted(m for m in sys.modules if m.startswith('odsplat.hil_sim')))"
    run = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 0 and run.stdout.strip() == "[]", run.stdout + run.stderr


def test_an_unknown_back_end_is_one_line_naming_the_known_ones(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text('[camera]\ndriver = "webcam"\n')
    with pytest.raises(InputError, match=r"camera.driver: expected one of opencv, photron, sim; got 'webcam'"):
        load_lab_config(lab)
    run = subprocess.run([sys.executable, "-m", "odsplat", "capture", str(tmp_path / "c"), "--config", str(lab)],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and "opencv, photron, sim" in run.stderr, run.stderr
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("camera, message", [
    ('driver = "opencv"\nip = "10.0.0.2"', r"camera.ip: the opencv back end takes no ip \(it takes source, fps"),
    ('driver = "photron"\nlibrary = "/nowhere/PDCLIB.so"', r"camera.ip: the photron back end needs it"),
])
def test_the_camera_keys_are_the_back_ends_keywords(tmp_path, camera, message):
    lab = tmp_path / "lab.toml"
    lab.write_text(f'[daq]\nurl = "/dev/null"\nchannels = [{{ name = "force", input = 0, kind = "force" }}]\n'
                   f'[camera]\n{camera}\n')
    with pytest.raises(InputError, match=message):
        load_lab_config(lab).open_camera()


@pytest.mark.parametrize("text, message", [
    (SIM_LAB + '[daq]\nurl = "/dev/ttyACM0"\n', r"lab.toml: \[daq\]: the simulated rig .* brings its own DAQ"),
    (SIM_LAB.replace("force_n", 'url = "/dev/ttyUSB1"\nforce_n'), r"lab.toml: hammer: .*camera.sim.hammer_link"),
    (SIM_LAB.replace('driver = "sim"', 'driver = "sim"\nfps = 500.0'), r"lab.toml: camera.fps: .*\[camera.sim\]"),
    (SIM_LAB.replace('driver = "sim"', 'driver = "opencv"'), r"lab.toml: camera.sim: .* driver = \"sim\" only"),
    (SIM_LAB.replace("seed = 3", "seeds = 3"), r"lab.toml: camera.sim: unknown field\(s\) \['seeds'\]"),
    (SIM_LAB.replace('driver = "sim"', 'driver = "sim"\nbackend = "sim"'), r"camera.backend: give driver or backend"),
])
def test_a_simulated_lab_file_refuses_what_the_rig_brings_itself(tmp_path, text, message):
    lab = tmp_path / "lab.toml"
    lab.write_text(text)
    with pytest.raises(InputError, match=message):
        load_lab_config(lab)


def _truth_peaks(cap: Capture) -> list[float]:
    takes = sorted(cap.manifest.takes, key=lambda t: t.created_utc)
    return [float(TakeTruth.load(truth_path(cap.root / t.file)).impact_peak_n[0]) for t in takes]


@pytest.mark.timeout(240)
def test_a_lab_file_with_the_sim_driver_runs_the_simulated_rig_as_capture_sim_does(tmp_path):
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    lab = tmp_path / "lab.toml"
    lab.write_text(SIM_LAB.replace('driver = "sim"', 'backend = "sim"'))   # the key's other name
    assert load_lab_config(lab).simulated
    by_lab = CliRunner().invoke(main, ["capture", str(tmp_path / "lab"), "--config", str(lab), "--auto", *SMALL],
                                env=env)
    assert by_lab.exit_code == 0, (by_lab.output, by_lab.exception)
    assert "1/1 views accepted" in by_lab.output and "double_hit x1" in by_lab.output
    cap = Capture.open(tmp_path / "lab")
    takes = sorted(cap.manifest.takes, key=lambda t: t.created_utc)
    assert [t.qc for t in takes] == ["rejected", "accepted"]   # take 0 bounced (the fault), redone
    with cap.open_take(takes[1].name) as r:
        assert r.frame_shape == (240, 320)                      # [camera.sim] size_px
        peak = float(np.nanmax(r.channel("force")))
    truth = _truth_peaks(cap)
    assert abs(truth[1] / 150 - 1) <= 0.03                      # [hammer] force_n, within QC's tolerance
    assert peak == pytest.approx(truth[1], rel=0.01)            # the DAQ records the rig's impact
    # The same rig from the command line's options: the same hits, take for take.
    by_flags = CliRunner().invoke(main, ["capture", str(tmp_path / "flags"), "--sim", "--auto", "--size", "320x240",
                                         "--seed", "3", "--sim-faults", "0:double_hit", "--hammer-force-n", "150",
                                         *SMALL], env=env)
    assert by_flags.exit_code == 0, (by_flags.output, by_flags.exception)
    assert _truth_peaks(Capture.open(tmp_path / "flags")) == truth
