"""The lab file's [can] section: `odsplat capture OUT --config LAB.toml` records the CAN accelerometer nodes it names
into every take, and bad values are refused naming the field.

The lab here is the simulated rig reached through real transports only: the DAQ on a PTY (`simdaq://`), the automatic
hammer on a PTY (`simhammer://`), a video file as the OpenCV camera, and hil_sim's CAN nodes speaking the node protocol
on a python-can `virtual` bus. Ground truth: the rig's modal model, its node mounts and the impacts of each take."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tomli_w
from click.testing import CliRunner

from odsplat.acquisition import CANNode, CANSetup, load_lab_config
from odsplat.acquisition import canproto as cp
from odsplat.app.cli import main
from odsplat.hil_sim.can_nodes import sim_nodes
from odsplat.hil_sim.daq import register_source, register_url_handler
from odsplat.hil_sim.hammer import hammer_url
from odsplat.hil_sim.rig import DEFAULT_CAN_NODES, RigConfig, SimRig
from odsplat.hil_sim.structure import Impact
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture

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


def _lab_text(daq_url: str, video: Path, hammer: str | None, can: dict) -> str:
    """A lab file as an engineer writes it, for the rig's DAQ inputs, the hammer (None: none) and the section `can`."""
    channels = [{k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(c).items() if v is not None}
                for c in SimRig(config=RigConfig(can_nodes=())).daq_channels()]
    return tomli_w.dumps({
        "daq": {"url": daq_url, "sample_rate_hz": 25600, "channels": channels},
        "camera": {"driver": "opencv", "source": str(video)},
        **({"hammer": {"url": hammer, "force_n": 200.0}} if hammer else {}),
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


@pytest.fixture(scope="module")
def lab_capture(tmp_path_factory, scene) -> tuple[Capture, SimRig, list[list[Impact]], str]:
    """`odsplat capture OUT --config lab.toml` over two views, the engineer pressing Enter at every prompt."""
    tmp = tmp_path_factory.mktemp("labcan")
    mounts = (DEFAULT_CAN_NODES[0], dataclasses.replace(DEFAULT_CAN_NODES[1], t0_s=NODE2_T0_S))
    rig = SimRig(scene, RigConfig(can_nodes=mounts, seed=5))
    impacts: list[list[Impact]] = []   # the hits of each take, kept when the next take's DAQ opens

    def fresh_take(**_: str) -> SimRig:
        # The DAQ is opened once per take; between takes time goes on and the structure comes to rest.
        impacts.append(list(rig.impacts))
        rig.new_take()
        return rig

    register_url_handler()
    name = f"lab-{rig.name}"
    register_source(name, fresh_take)
    channel = f"labcan-{rig.name}-{id(tmp)}"
    lab = tmp / "lab.toml"
    lab.write_text(_lab_text(f"simdaq://{name}?fs=51200", _video(tmp / "camera.avi"), hammer_url(rig, seed=5),
                             _can_section(channel)))
    out = tmp / "cap"
    with sim_nodes(channel, [1, 2], rig, sample_rate_hz=CAN_RATE_HZ, range_m_s2=RANGE_G * 9.80665, paced=True) as nodes:
        run = CliRunner().invoke(main, ["capture", str(out), "--config", str(lab), "--views", "2", "--frames", "6",
                                        "--pretrigger-frames", "2", "--record-s", "0.3", "--no-window"],
                                 input="\n" * 8)
        assert all(n.dropped_samples == [] and n.overrun_samples == [] for n in nodes)
    assert run.exit_code == 0, (run.output, run.exception)
    impacts.append(list(rig.impacts))
    return Capture.open(out), rig, impacts[1:], run.output


def test_lab_file_capture_records_the_can_nodes_into_every_take(lab_capture):
    cap, rig, impacts, output = lab_capture
    assert "2/2 views accepted" in output
    takes = cap.manifest.takes
    assert len(takes) == len(impacts) and all(t.qc == "accepted" for t in takes)
    # The manifest places the channels as the lab file says.
    chans = {c.name: c for c in cap.manifest.channels}
    for axis, direction in zip("xyz", ([0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0])):
        c = chans[f"node2_{axis}"]
        assert c.direction == direction and c.position_m == [0.0, 0.045, 0.5]
        assert (c.source, c.node, c.sample_rate_hz, c.unit) == ("can:node2", 2, CAN_RATE_HZ, "m/s^2")
    assert chans["node1_z"].direction == [0.0, 0.0, 1.0] and chans["node1_z"].position_m == [0.25, 0.0, 0.6]
    lsb = RANGE_G * 9.80665 / cp.FULL_SCALE_COUNTS
    worst = 0.0
    for take, hits in zip(takes, impacts):
        assert len(hits) >= 1
        with cap.open_take(take.name) as r:
            assert r.can_nodes == ["node1", "node2"]
            daq_start, daq_stop = r.daq_t0_s, r.daq_t0_s + r.n_samples / r.sample_rate_hz
            for mount in rig.config.can_nodes:
                node = f"node{mount.node_id}"
                assert r.can_sample_rate_hz(node) == CAN_RATE_HZ
                t, _ = r.can_channel(f"{node}_x")
                x = np.stack([r.can_channel(f"{node}_{a}")[1] for a in "xyz"], axis=1).astype(float)
                # at the node's rate, covering the DAQ's record and the resampling kernel's reach
                np.testing.assert_allclose(np.diff(t), 1 / CAN_RATE_HZ, rtol=1e-9)
                assert t[0] <= daq_start - 16 / CAN_RATE_HZ and t[-1] >= daq_stop + 16 / CAN_RATE_HZ
                assert not np.isnan(x).any()
                # The samples are the rig's true acceleration along the node's axes at the stored times (on the
                # DAQ's time base, from t0_daq_s), to the node's quantisation.
                qdd = rig.structure.modal_response(hits, t).qdd
                phi = rig.structure.mode_shapes(np.asarray(mount.point_m)[None])[0]
                want = np.einsum("kc,kt->tc", phi, qdd) @ np.asarray(mount.axes).T
                assert np.abs(want).max() > 1000 * lsb  # the hit is in the record
                worst = max(worst, float(np.max(np.abs(x - want))))
    print(f"CAN samples vs the rig's truth over {len(takes)} takes: worst error {worst:.4f} m/s^2 "
          f"({worst / lsb:.2f} LSB)")
    assert worst <= 0.5 * lsb + 1e-4


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
    run = subprocess.run([sys.executable, "-m", "odsplat", "capture", str(tmp_path / "c"), "--config", str(lab)],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2
    assert run.stderr == f"odsplat: error: {lab}: can.nodes[1].t0_daq_s: required field is missing\n"
    assert not (tmp_path / "c").exists()


def test_a_can_bus_that_cannot_open_stops_the_capture_before_the_first_view(tmp_path):
    lab = tmp_path / "lab.toml"
    lab.write_text(_lab_text("/dev/ttyACM0", _video(tmp_path / "camera.avi", n=4), None,
                             dict(_can_section("can0"), interface="nosuch")))
    run = CliRunner().invoke(main, ["capture", str(tmp_path / "c"), "--config", str(lab), "--no-window"], input="\n")
    assert run.exit_code == 2, run.output
    assert "odsplat: error: CAN bus nosuch:can0: cannot open" in run.output and "Place the camera" not in run.output
    assert not (tmp_path / "c").exists()


def test_the_lab_file_example_in_the_docs_loads(tmp_path):
    doc = (REPO / "docs" / "acquisition.md").read_text()
    example = doc.split("### The lab file", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    lab = tmp_path / "lab.toml"
    lab.write_text(example)
    cfg = load_lab_config(lab)
    assert cfg.can_bus == {"interface": "socketcan", "channel": "can0", "bitrate": 1_000_000}
    assert cfg.can.nodes[1].axes == ((0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    assert cfg.can.nodes[0].axes == ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
