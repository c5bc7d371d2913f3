"""CAN accelerometer nodes in the capture store: their own group per node at their own rate, read raw or on the
DAQ's grid, older takes still read, bad input named, and nothing flushed lost when the writer is killed (SIGKILL)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from odsplat.acquisition import CANNode, CANSetup
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import ChannelInfo, Manifest
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader
from odsplat.spine.timebase import resample_onto

DAQ_RATE_HZ = 10240.0
CAN_RATE_HZ = 500.0
NODE = CANNode(3, (0.1, 0.0, 0.5), ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), t0_daq_s=0.0071)


def _manifest() -> Manifest:
    daq = [ChannelInfo("force", "force", "N"),
           ChannelInfo("acc1", "acceleration", "m/s^2", position_m=[0.3, 0.0, 0.5], direction=[0, 1, 0])]
    return Manifest(name="can", daq_sample_rate_hz=DAQ_RATE_HZ, channels=daq + NODE.channels(CAN_RATE_HZ))


def _tone(t_s: np.ndarray, axis: int) -> np.ndarray:
    """A node's signal: tones well inside its band (0.42 x 500 Hz), one set per axis."""
    return 3.0 * np.sin(2 * np.pi * (37.0 + 50 * axis) * t_s) + np.cos(2 * np.pi * (131.0 + 20 * axis) * t_s)


def test_can_channels_round_trip_at_their_own_rate_and_on_the_daq_grid(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    daq_t0 = 0.05
    n_daq = 4096                                                  # 0.4 s
    k = np.arange(240)                                            # covers the DAQ's record with 17+ to spare
    t_can = NODE.t0_daq_s + k / CAN_RATE_HZ
    with cap.new_take("t0", daq_t0_s=daq_t0) as w:
        w.append_samples({"force": np.zeros(n_daq), "acc1": np.ones(n_daq)})
        for a in range(0, len(k), 100):                           # blocks, as the session's reader delivers them
            sl = slice(a, a + 100)
            w.append_can_samples("node3", t_can[sl], {f"node3_{ax}": _tone(t_can[sl], i) for i, ax in
                                                      enumerate("xyz")})
        record = w.finalize()
    assert record.n_samples == n_daq
    with h5py.File(cap.root / record.file) as f:                  # the layout docs/store.md describes
        assert f.attrs["odsplat_schema"] == "1.1"
        assert json.loads(f["can"].attrs["node_order"]) == ["node3"]
        assert f["can/node3"].attrs["sample_rate_hz"] == CAN_RATE_HZ and f["can/node3"].attrs["source"] == "can:node3"
        assert f["can/node3/times_s"].dtype == np.float64 and f["can/node3/node3_z"].dtype == np.float32
    assert [c.source for c in Capture.open(cap.root).manifest.channels] == ["daq"] * 2 + ["can:node3"] * 3
    with cap.open_take("t0") as r:
        assert r.channel_names == ["force", "acc1"]               # the DAQ's, as before
        assert r.can_nodes == ["node3"] and r.can_channel_names == ["node3_x", "node3_y", "node3_z"]
        info = r.channel_info("node3_y")
        assert info.source == "can:node3" and info.sample_rate_hz == CAN_RATE_HZ and info.direction == [0, 1, 0]
        times, values = r.can_channel("node3_y")
        np.testing.assert_array_equal(times, t_can)
        np.testing.assert_allclose(values, _tone(t_can, 1), atol=1e-5)
        on_grid = r.channel("node3_y")
        grid = daq_t0 + np.arange(n_daq) / DAQ_RATE_HZ
        assert on_grid.shape == (n_daq,) and on_grid.dtype == np.float32
        err = np.abs(on_grid - _tone(grid, 1))
        assert err.max() < 1e-3 * 4.0, err.max()                  # band-limited: the kernel's ripple, float32
    # outside the CAN record: NaN; at its ends: linear, then band-limited inside
    y = resample_onto(_tone(t_can, 0), t_can[0], CAN_RATE_HZ, np.array([t_can[0] - 1e-4, t_can[0], t_can[-1] + 1e-4]))
    assert np.isnan(y[0]) and y[1] == pytest.approx(_tone(t_can[:1], 0)[0]) and np.isnan(y[2])


def test_a_take_of_schema_1_0_reads_as_before(tmp_path):
    """A take written before CAN nodes were stored: no /can group, channel entries without source."""
    cap = Capture.create(tmp_path / "cap", Manifest(name="old", daq_sample_rate_hz=DAQ_RATE_HZ,
                                                    channels=_manifest().channels[:2]))
    with cap.new_take("old") as w:
        w.append_samples({"force": np.arange(64.0), "acc1": np.zeros(64)})
        record = w.finalize()
    with h5py.File(cap.root / record.file, "r+") as f:
        f.attrs["odsplat_schema"] = "1.0"
        for name in ("force", "acc1"):
            info = json.loads(f["daq"][name].attrs["info"])
            del info["source"], info["sample_rate_hz"]
            f["daq"][name].attrs["info"] = json.dumps(info)
    with TakeReader(cap.root / record.file) as r:
        assert r.can_nodes == [] and r.can_channel_names == []
        assert r.channel_info("acc1").source == "daq" and r.channel("force")[-1] == 63.0


def test_bad_can_input_names_the_device_or_field():
    with pytest.raises(InputError, match=r"^CAN node 17: unknown to accel_nodes.dbc, which defines nodes 1..16$"):
        CANNode(17)
    with pytest.raises(InputError, match=r"^CANSetup.sample_rate_hz: 0 is not one of"):
        CANSetup((NODE,), sample_rate_hz=0.0)
    bad = ChannelInfo("n_x", "acceleration", "m/s^2", source="can:n", sample_rate_hz=0.0)
    with pytest.raises(InputError, match=r"channels\[0\].sample_rate_hz: a CAN channel needs its node's sample rate"):
        Manifest(name="x", channels=[bad]).validate("capture.json")
    with pytest.raises(InputError, match=r"channels\[0\].source: expected 'daq' or 'can:NODE'"):
        Manifest(name="x", channels=[ChannelInfo("a", "acceleration", "m/s^2", source="usb")]).validate("capture.json")


_WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_store_can import _manifest
    from odsplat.spine.store import Capture
    cap = Capture.create({root!r}, _manifest())
    w = cap.new_take("dying", frame_shape=(16, 16), dtype=np.uint8)
    for k in range(1000000):
        w.append_frames(np.full((16, 16), k % 251, np.uint8))
        w.append_samples({{"force": np.full(64, k, "f4"), "acc1": np.zeros(64, "f4")}})
        s = np.arange(4 * k, 4 * k + 4)
        w.append_can_samples("node3", 0.0071 + s / 500.0, {{"node3_x": s, "node3_y": -s, "node3_z": 2 * s}})
        print(4 * k + 4, flush=True)
    """
)


@pytest.mark.timeout(120)
def test_sigkill_mid_take_loses_no_flushed_can_sample(tmp_path):
    root = tmp_path / "cap"
    script = _WRITER.format(tests=str(Path(__file__).parent), root=str(root))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    announced = 0
    deadline = time.monotonic() + 60
    for line in proc.stdout:
        announced = int(line)
        if announced >= 400 or time.monotonic() > deadline:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert announced >= 400
    cap = Capture.open(root)
    (report,) = cap.recover()
    assert report.recovered, report.message
    with cap.open_take("dying") as r:
        times, x = r.can_channel("node3_x")
        n = len(times)
        assert n >= announced                                  # every block announced was flushed
        s = np.arange(n)
        np.testing.assert_array_equal(x, s)
        np.testing.assert_array_equal(r.can_channel("node3_z")[1], 2 * s)
        np.testing.assert_allclose(times, 0.0071 + s / 500.0, rtol=0, atol=1e-12)
        assert r.can_sample_rate_hz("node3") == CAN_RATE_HZ and r.channel_info("node3_y").source == "can:node3"
