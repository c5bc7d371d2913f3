"""The lab file's [can] section: the CAN accelerometer nodes it names, and bad values refused naming the field."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w

from odsplat.acquisition import CANNode, CANSetup, load_lab_config
from odsplat.acquisition import canproto as cp
from odsplat.errors import InputError
from odsplat.hil_sim.rig import DEFAULT_CAN_NODES, RigConfig, SimRig

pytestmark = pytest.mark.timeout(120)

REPO = Path(__file__).resolve().parents[2]
CAN_RATE_HZ = 1000.0
RANGE_G = 50
NODE2_T0_S = 0.0123  # node 2 starts 12.3 ms after the DAQ: stored times that ignored it would be 12 samples off
NODE2_DIRECTION = ["+Y", "-X", "+Z"]  # DEFAULT_CAN_NODES[1].axes, as a lab file writes them


def _video(path: Path, n: int = 200, fps: float = 100.0) -> Path:
    """2 s of small grey frames: the OpenCV camera's source (the camera is not under test)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (64, 48))
    assert writer.isOpened()
    for i in range(n):
        writer.write(np.full((48, 64, 3), i % 256, np.uint8))
    writer.release()
    return path


def _lab_text(daq_url: str, video: Path, hammer: str, can: dict) -> str:
    """A lab file as an engineer writes it, for the rig's DAQ inputs, the hammer and the CAN section `can`."""
    channels = [{k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(c).items() if v is not None}
                for c in SimRig(config=RigConfig(can_nodes=())).daq_channels()]
    return tomli_w.dumps({
        "daq": {"url": daq_url, "sample_rate_hz": 25600, "channels": channels},
        "camera": {"driver": "opencv", "source": str(video)},
        "hammer": {"url": hammer, "force_n": 200.0},
        "can": can,
    })


def _can_section(channel: str) -> dict:
    n1, n2 = DEFAULT_CAN_NODES
    return {"interface": "virtual", "channel": channel, "bitrate": 1_000_000, "sample_rate_hz": CAN_RATE_HZ,
            "range_g": RANGE_G,
            "nodes": [{"node_id": 1, "position_m": list(n1.point_m), "direction": [list(a) for a in n1.axes],
                       "t0_daq_s": 0.0},
                      {"node_id": 2, "position_m": list(n2.point_m), "direction": NODE2_DIRECTION,
                       "t0_daq_s": NODE2_T0_S}]}


def test_can_section_parses_to_the_nodes_and_the_bus(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text(_lab_text("/dev/ttyACM0", tmp_path / "x.avi", "/dev/ttyUSB1", _can_section("can7")))
    cfg = load_lab_config(lab)
    assert cfg.can_bus == {"interface": "virtual", "channel": "can7", "bitrate": 1_000_000}
    mounted = tuple(CANNode(m.node_id, m.point_m, m.axes, t0) for m, t0 in zip(DEFAULT_CAN_NODES, (0.0, NODE2_T0_S)))
    assert cfg.can == CANSetup(mounted, CAN_RATE_HZ, cp.RANGES_M_S2[4])
    # range_m_s2 instead of range_g, python-can's own configuration for the bus, and a node with no mount given
    section = _can_section("can7")
    for key in ("interface", "channel", "bitrate", "range_g"):
        section.pop(key)
    section.update(range_m_s2=156.9, nodes=[{"node_id": 3, "t0_daq_s": -0.002}])
    lab.write_text(_lab_text("/dev/ttyACM0", tmp_path / "x.avi", "/dev/ttyUSB1", section))
    cfg = load_lab_config(lab)
    assert cfg.can_bus == {} and cfg.can.range_m_s2 == cp.RANGES_M_S2[3]
    (node,) = cfg.can.nodes
    assert (node.node_id, node.position_m, node.axes, node.t0_daq_s) == (3, None, None, -0.002)


def _node(i: int, **change) -> dict:
    section = _can_section("can0")
    section["nodes"][i].update(change)
    return section


BAD = [
    (dict(_can_section("can0"), sample_rate_hz=1200), r"can.sample_rate_hz: 1200 is not one of \[250.0, 500.0"),
    (dict(_can_section("can0"), range_g=60), r"can.range_g: 60 is not one of \[2, 4, 8, 16, 50, 100, 200, 500\]"),
    (dict(_can_section("can0"), range_m_s2=490.3325), r"can.range_g: give range_g or range_m_s2, not both"),
    (dict(_can_section("can0"), bitrate=125_000), r"can.sample_rate_hz: 2 node\(s\) at 1000 Hz take 216% of a 125000"),
    (dict(_can_section("can0"), nodes=[]), r"can.nodes: no node"),
    (dict(_can_section("can0"), channel=[0]), r"can.channel: expected a name or a number"),
    (dict(_can_section("can0"), speed=1), r"can: unknown field\(s\) \['speed'\]"),
    (_node(1, node_id=17), r"can.nodes\[1\].node_id: 17 is outside 1..16"),
    (_node(1, node_id=1), r"can.nodes\[1\].node_id: 1 is also can.nodes\[0\]'s"),
    (_node(0, node_id="one"), r"can.nodes\[0\].node_id: expected an integer"),
    (_node(0, position_m=[0.1, 0.2]), r"can.nodes\[0\].position_m: expected 3 values"),
    (_node(1, direction=["+Y", "+X", "+Z"]), r"can.nodes\[1\].direction: a left-handed set"),
    (_node(1, direction=["+Y", "+Y", "+Z"]), r"can.nodes\[1\].direction: the node's axes must be perpendicular"),
    (_node(1, direction=["up", "-X", "+Z"]), r"can.nodes\[1\].direction\[0\]: expected one of \+X"),
    (_node(1, direction=[[0, 2, 0], "-X", "+Z"]), r"can.nodes\[1\].direction\[0\]: expected a unit vector"),
    (_node(1, direction="+Z"), r"can.nodes\[1\].direction: expected the node's x, y and z axes"),
    (_node(1, t0_daq_s=12.3), r"can.nodes\[1\].t0_daq_s: expected the node's start .* got 12.3"),
]


@pytest.mark.parametrize("section,message", BAD, ids=[m.split(":")[0].replace("\\", "") for _, m in BAD])
def test_bad_can_values_are_refused_naming_the_field(tmp_path, section, message):
    lab = tmp_path / "lab.toml"
    lab.write_text(_lab_text("/dev/ttyACM0", tmp_path / "x.avi", "/dev/ttyUSB1", section))
    with pytest.raises(InputError, match=r"lab.toml: " + message):
        load_lab_config(lab)


def test_a_missing_t0_is_refused_and_the_cli_says_so_in_one_line(tmp_path):
    section = _can_section("can0")
    del section["nodes"][1]["t0_daq_s"]
    lab = tmp_path / "lab.toml"
    lab.write_text(_lab_text("/dev/ttyACM0", tmp_path / "x.avi", "/dev/ttyUSB1", section))
    run = subprocess.run([sys.executable, "-m", "odsplat.cli", "capture", str(tmp_path / "c"), "--config", str(lab)],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2
    assert run.stderr == f"odsplat: error: {lab}: can.nodes[1].t0_daq_s: required field is missing\n"
    assert not (tmp_path / "c").exists()
