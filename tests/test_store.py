"""The capture store: round trips, schema checks, streaming reads and crash safety under SIGKILL."""
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

from odsplat.spine.errors import IncompleteTakeError, InputError, SchemaError
from odsplat.spine.manifest import CameraInfo, ChannelInfo, Manifest
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader
from odsplat.spine.take_writer import QCInfo, TriggerInfo

CHANNELS = [
    ChannelInfo("force", "force", "N", sensitivity_v_per_unit=2.25e-3, position_m=[0.1, 0.0, 0.5],
                direction=[0, 0, -1]),
    ChannelInfo("acc1", "acceleration", "m/s^2", position_m=[0.3, 0.0, 0.5], direction=[0, 1, 0]),
]


def _frame(k: int, shape=(48, 64)) -> np.ndarray:
    """A deterministic 12-bit frame whose content identifies its index."""
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return ((xx * 37 + yy * 11 + k * 101) % 4096).astype(np.uint16)


def _manifest() -> Manifest:
    return Manifest(name="unit", camera=CameraInfo(model="test", width_px=64, height_px=48, fps=1000.0, bit_depth=12),
                    daq_sample_rate_hz=10240.0, channels=CHANNELS)


def test_take_round_trip(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    times = np.arange(20) / 1000.0 - 0.005
    force = np.sin(np.arange(2048) / 10).astype("f4")
    with cap.new_take(view=3, frame_shape=(48, 64), dtype=np.uint16, bit_depth=12, fps=1000.0) as w:
        for k in range(20):
            w.append_frames(_frame(k), times_s=[times[k]], counter=[k - 5])
        w.append_samples({"force": force[:1024], "acc1": np.zeros(1024)})
        w.append_samples({"force": force[1024:], "acc1": np.ones(1024)})
        w.set_trigger(TriggerInfo(trigger_sample=256, pretrigger_samples=256, camera_trigger_frame=5,
                                  trigger_time_s=0.0))
        w.set_qc(QCInfo("accepted", ("ok",), "fine"))
        record = w.finalize()
    assert record.name == "v03_000" and record.view == 3 and record.n_frames == 20 and record.n_samples == 2048
    assert not list(cap.takes_dir.glob("*.partial"))

    cap2 = Capture.open(cap.root)
    assert cap2.take_names() == ["v03_000"]
    with cap2.open_take("v03_000") as r:
        assert r.n_frames == 20 and r.frame_shape == (48, 64) and r.bit_depth == 12 and r.fps == 1000.0
        np.testing.assert_array_equal(r.read_frames(7, 8)[0], _frame(7))
        blocks = list(r.iter_frames(chunk_frames=6))
        assert [len(b) for b in blocks] == [6, 6, 6, 2]
        np.testing.assert_array_equal(np.concatenate(blocks)[19], _frame(19))
        np.testing.assert_allclose(r.frame_times_s, times)
        np.testing.assert_array_equal(r.frame_counter, np.arange(20) - 5)
        np.testing.assert_array_equal(r.channel("force"), force)
        assert r.channel("acc1").sum() == 1024
        assert r.channel_info("force").sensitivity_v_per_unit == pytest.approx(2.25e-3)
        assert r.trigger == TriggerInfo(256, 256, 5, 0.0)
        assert r.qc == QCInfo("accepted", ("ok",), "fine")
        assert r.sample_rate_hz == 10240.0 and r.view == 3
        with pytest.raises(InputError, match="no DAQ channel 'acc9'"):
            r.channel("acc9")


def test_frames_are_chunked_and_compressed(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    with cap.new_take("t", frame_shape=(48, 64), dtype=np.uint16, bit_depth=12) as w:
        for k in range(10):
            w.append_frames(np.zeros((48, 64), np.uint16) + k)
        w.finalize()
    with h5py.File(cap.takes_dir / "t.h5") as f:
        ds = f["frames"]
        assert ds.chunks == (1, 48, 64)
        assert "32001" in ds._filters  # Blosc
        assert ds.id.get_storage_size() < 10 * 48 * 64 * 2 / 20


def test_raw_takes_are_written_once(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    with cap.new_take("t", channels=[]) as w:
        w.finalize()
    with pytest.raises(Exception, match="exists already"):
        cap.new_take("t", channels=[])


def test_a_take_killed_while_being_created_is_set_aside_not_left_in_the_way(tmp_path):
    """A SIGKILL before HDF5 wrote the header leaves an empty or headless `.partial`: nothing was recorded in it, but
    resume must not trip over it, and it is kept. A file another process holds open is left alone."""
    cap = Capture.create(tmp_path / "cap", _manifest())
    cap.takes_dir.mkdir(exist_ok=True)
    (cap.takes_dir / "empty.h5.partial").write_bytes(b"")
    with h5py.File(cap.takes_dir / "headless.h5.partial", "w", libver="latest") as f:
        f.attrs.update({"odsplat_schema": "1.0", "kind": "take"})  # killed before its groups were made
    busy = cap.takes_dir / "busy.h5.partial"
    holder = subprocess.Popen([sys.executable, "-c", "import h5py, sys, time; f = h5py.File(sys.argv[1], 'w'); "
                               "print('open', flush=True); time.sleep(60)", str(busy)], stdout=subprocess.PIPE,
                              text=True)
    try:
        assert holder.stdout.readline().strip() == "open"
        reports = {r.name: r for r in cap.recover()}
    finally:
        holder.kill()
        holder.wait()
    assert set(reports) == {"busy", "empty", "headless"}
    assert not any(r.recovered for r in reports.values())
    assert "in use by another process" in reports["busy"].message and busy.exists()
    assert "unreadable as HDF5" in reports["empty"].message
    assert "before any frame or sample was written" in reports["headless"].message
    for name in ("empty", "headless"):
        assert (cap.takes_dir / f"{name}.h5.crashed").exists() and reports[name].path.name == f"{name}.h5.crashed"
    assert cap.partial_takes() == [busy] and cap.take_names() == []
    assert not list(cap.takes_dir.glob("*recovering*"))


def test_reader_refuses_unknown_major_version(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    with cap.new_take("t", channels=[]) as w:
        w.finalize()
    path = cap.takes_dir / "t.h5"
    with h5py.File(path, "r+") as f:
        f.attrs["odsplat_schema"] = "2.0"
    with pytest.raises(SchemaError, match=r"t\.h5.*major 2.*upgrade odsplat"):
        TakeReader(path)
    with h5py.File(tmp_path / "foreign.h5", "w") as f:
        f["x"] = 1
    with pytest.raises(SchemaError, match="not an odsplat take"):
        TakeReader(tmp_path / "foreign.h5")


def test_manifest_errors_name_the_field(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    data = json.loads((cap.root / "capture.json").read_text())
    data["channels"][1]["kind"] = "strain"
    (cap.root / "capture.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"channels\[1\]\.kind: expected one of force"):
        Capture.open(cap.root)
    data["channels"][1]["kind"] = "acceleration"
    data["schema_version"] = "7.1"
    (cap.root / "capture.json").write_text(json.dumps(data))
    with pytest.raises(SchemaError, match="major 7"):
        Capture.open(cap.root)
    data["schema_version"] = "1.3"
    data["camera"]["fps"] = "fast"
    (cap.root / "capture.json").write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"camera\.fps: expected a number"):
        Capture.open(cap.root)


def test_unfinished_take_is_not_read_silently(tmp_path):
    cap = Capture.create(tmp_path / "cap", _manifest())
    w = cap.new_take("t", frame_shape=(48, 64), dtype=np.uint16, bit_depth=12)
    w.append_frames(_frame(0))
    w.close_unfinished()
    with pytest.raises(IncompleteTakeError, match="odsplat recover"):
        TakeReader(w.partial_path)
    assert cap.take_names() == []
    assert cap.partial_takes() == [w.partial_path]


_WRITER = textwrap.dedent(
    """
    import sys, numpy as np
    sys.path.insert(0, {tests!r})
    from test_store import _frame, _manifest
    from odsplat.spine.store import Capture
    cap = Capture.create({root!r}, _manifest())
    for t in range(2):
        with cap.new_take(f"done{{t}}", view=t, frame_shape=(48, 64), dtype=np.uint16, bit_depth=12) as w:
            for k in range(30):
                w.append_frames(_frame(k + 1000 * t))
            w.append_samples({{"force": np.full(4096, t, "f4"), "acc1": np.arange(4096, dtype="f4")}})
            w.finalize()
    w = cap.new_take("dying", view=2, frame_shape=(48, 64), dtype=np.uint16, bit_depth=12)
    for k in range(100000):
        w.append_frames(_frame(k + 2000))
        if k % 64 == 0:
            w.append_samples({{"force": np.full(64, 2, "f4"), "acc1": np.full(64, k, "f4")}})
        print(k, flush=True)
    """
)


def test_sigkill_mid_take_loses_nothing_flushed(tmp_path):
    root = tmp_path / "cap"
    script = _WRITER.format(tests=str(Path(__file__).parent), root=str(root))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    last = -1
    deadline = time.monotonic() + 120
    for line in proc.stdout:
        last = int(line)
        if last >= 150 or time.monotonic() > deadline:
            break
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert last >= 150

    cap = Capture.open(root)
    # Finished takes are intact and listed.
    assert cap.take_names() == ["done0", "done1"]
    for t in range(2):
        with cap.open_take(f"done{t}") as r:
            assert r.n_frames == 30 and not r.recovered
            np.testing.assert_array_equal(r.read_frames(29, 30)[0], _frame(29 + 1000 * t))
            assert r.channel("force").tolist() == [t] * 4096
    # The partial one is reported and refused until recovered.
    partial = cap.takes_dir / "dying.h5.partial"
    assert cap.partial_takes() == [partial]
    with pytest.raises(IncompleteTakeError):
        TakeReader(partial)

    (report,) = cap.recover()
    assert report.recovered, report.message
    assert report.n_frames >= last + 1  # every frame announced as written was flushed
    assert (cap.takes_dir / "dying.h5.crashed").exists()  # the original is kept
    assert cap.partial_takes() == []
    assert "dying" in Capture.open(root).take_names()
    with cap.open_take("dying") as r:
        assert r.recovered and "recovered" in r.qc.flags and r.view == 2
        assert r.n_frames == report.n_frames
        frames = np.concatenate(list(r.iter_frames(chunk_frames=50)))
        for k in (0, last, r.n_frames - 1):
            np.testing.assert_array_equal(frames[k], _frame(k + 2000))
        assert np.all(r.channel("force") == 2) and r.n_samples >= 64 * (last // 64)
