"""The `odsplat` command: help everywhere, one-line errors, info and recover on real captures."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from odsplat.spine.manifest import ChannelInfo, Manifest
from odsplat.spine.store import Capture


def odsplat(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "odsplat", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("sub", [[], ["info"], ["import"], ["recover"]])
def test_help_on_every_subcommand(sub):
    out = odsplat(*sub, "--help")
    assert out.returncode == 0 and "Usage: " in out.stdout


def _capture(root):
    cap = Capture.create(root, Manifest(name="cli", daq_sample_rate_hz=1000.0,
                                        channels=[ChannelInfo("force", "force", "N")]))
    with cap.new_take("a", view=1, frame_shape=(8, 8), dtype=np.uint8, fps=500.0) as w:
        for k in range(10):
            w.append_frames(np.full((8, 8), k, np.uint8))
        w.append_samples({"force": np.zeros(100)})
        w.finalize()
    w = cap.new_take("b", view=2, frame_shape=(8, 8), dtype=np.uint8, fps=500.0)
    w.append_frames(np.ones((3, 8, 8), np.uint8))
    w.close_unfinished()
    return cap


def test_info_and_recover(tmp_path):
    cap = _capture(tmp_path / "cap")
    out = odsplat("info", str(cap.root))
    assert out.returncode == 0, out.stderr
    assert "a " in out.stdout and "unfinished take b.h5.partial" in out.stdout
    data = json.loads(odsplat("info", "--json", str(cap.root)).stdout)
    (take,) = data["takes"]
    assert (take["name"], take["n_frames"], take["duration_s"], take["n_samples"]) == ("a", 10, 0.02, 100)

    out = odsplat("recover", str(cap.root))
    assert out.returncode == 0 and "b: recovered" in out.stdout and "3 frames" in out.stdout
    data = json.loads(odsplat("info", "--json", str(cap.root)).stdout)
    assert [t["name"] for t in data["takes"]] == ["a", "b"] and data["unfinished"] == []
    assert data["takes"][1]["status"] == "recovered" and data["takes"][1]["qc_flags"] == ["recovered"]


def test_errors_are_one_line(tmp_path):
    out = odsplat("info", str(tmp_path / "nope"))
    assert out.returncode == 2 and out.stderr.strip().count("\n") == 0 and "nope: no such capture" in out.stderr
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "x"\n[[takes]]\nvideo = "missing.cih"\n')
    out = odsplat("import", str(rig), "-o", str(tmp_path / "cap"))
    assert out.returncode == 2 and out.stderr.strip().count("\n") == 0 and "missing" in out.stderr
    assert not (tmp_path / "cap").exists()


def test_a_truncated_cine_is_one_line_and_exit_2(shared_data, tmp_path):
    data = (shared_data / "pyidi-samples" / "data_small_cine.cine").read_bytes()
    (tmp_path / "take.cine").write_bytes(data[:-5000])
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "x"\n[[takes]]\nvideo = "take.cine"\n')
    out = odsplat("import", str(rig), "-o", str(tmp_path / "cap"))
    assert out.returncode == 2 and out.stderr.strip().count("\n") == 0, out.stderr
    assert "take.cine: truncated: holds 2417424 bytes, 234 whole frames of the 235" in out.stderr
    assert "Traceback" not in out.stderr and not (tmp_path / "cap").exists()
    assert not list(tmp_path.glob(".cap.importing-*"))
