"""`odsplat import`: real recordings into a capture; bad input stops with one line and leaves nothing."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from odsplat.errors import InputError
from odsplat.importer import import_capture
from odsplat.store import Capture

REPO = Path(__file__).resolve().parents[1]


def _nothing_left(out: Path) -> bool:
    return not out.exists() and not list(out.parent.glob(f".{out.name}.importing-*"))


def test_ladisk_example_rig(shared_data, tmp_path):
    out = tmp_path / "beam"
    cap = import_capture(REPO / "examples" / "ladisk-beam.toml", out, data_dir=shared_data)
    assert cap.root == out and Capture.open(out).take_names() == ["hit_acc", "hit_cam", "showcase"]
    m = cap.manifest
    assert m.daq_sample_rate_hz == pytest.approx(50_000.0)
    assert (m.camera.width_px, m.camera.height_px, m.camera.bit_depth) == (640, 40, 8)
    with cap.open_take("hit_acc") as r:
        assert r.n_samples == 50_030 and not r.has_frames
        assert r.channel("force")[0] == pytest.approx(0.232147, rel=1e-6)
        assert r.channel("acc")[0] == pytest.approx(-0.007387 * 9.80665, rel=1e-6)
        assert r.channel_info("acc").unit == "m/s^2"
        assert r.trigger.trigger_sample == 30 and r.trigger.trigger_time_s == pytest.approx(30 / 50_000)
        # The hammer hit lies just after the 30 pre-samples.
        assert 30 <= int(np.argmax(r.channel("force"))) < 200
    with cap.open_take("showcase") as r:
        assert (r.n_frames, r.frame_shape, r.frames.dtype) == (75, (40, 640), np.uint8)
        assert r.fps == pytest.approx(m.camera.fps) and r.view == 0
        raw = np.fromfile(shared_data / "pyidi-samples" / "data_showcase.mraw", dtype=np.uint8).reshape(75, 40, 640)
        np.testing.assert_array_equal(np.concatenate(list(r.iter_frames(16))), raw)


def test_truncated_mraw_leaves_nothing(shared_data, tmp_path):
    src = shared_data / "pyidi-samples"
    shutil.copy(src / "data_showcase.cih", tmp_path / "cam.cih")
    (tmp_path / "cam.mraw").write_bytes((src / "data_showcase.mraw").read_bytes()[:-1000])
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "t"\n[[takes]]\nvideo = "cam.cih"\n')
    out = tmp_path / "cap"
    with pytest.raises(InputError, match=r"cam\.mraw.*truncated"):
        import_capture(rig, out)
    assert _nothing_left(out)


def _write_sequence(folder: Path, n: int) -> np.ndarray:
    folder.mkdir()
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 4096, size=(n, 24, 32), dtype=np.uint16)
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"img_{k}.png"), frame)
    return frames


def _write_csv(path: Path, n: int, fs: float, bad: str = "") -> None:
    t = np.arange(n) / fs
    force = np.exp(-(((t - 0.01) / 0.0005) ** 2)) * 100.0
    acc = np.sin(2 * np.pi * 80 * t)
    lines = ["time [s],hammer [N],acc1 [g]"] + [f"{a:.8f},{b:.6f},{c:.6f}" for a, b, c in zip(t, force, acc)]
    if bad == "nan":
        lines[40] = lines[40].rsplit(",", 1)[0] + ",nan"
    path.write_text("\n".join(lines) + "\n")


def _rig(tmp_path: Path, extra_channel: str = "") -> Path:
    rig = tmp_path / "rig.toml"
    rig.write_text(
        'name = "seq"\n'
        '[[channels]]\nname = "force"\nkind = "force"\ncolumn = "hammer"\n'
        '[[channels]]\nname = "acc1"\nkind = "acceleration"\nposition_m = [0.1, 0.2, 0.3]\ndirection = [0, 0, 1]\n'
        + extra_channel +
        '[[takes]]\nname = "hit"\nview = 4\nvideo = "seq"\nsignals = "daq.csv"\nfps = 1000.0\n'
        'pretrigger_samples = 200\ncamera_trigger_time_s = 0.0095\n'
    )
    return rig


def test_sequence_and_csv_with_frame_times(tmp_path):
    frames = _write_sequence(tmp_path / "seq", 12)
    _write_csv(tmp_path / "daq.csv", 2000, 20_000.0)
    cap = import_capture(_rig(tmp_path), tmp_path / "cap")
    with cap.open_take("hit") as r:
        np.testing.assert_array_equal(r.read_frames(), frames)
        # 16-bit PNGs of values below 4096: 12 bits, found in the data.
        assert r.bit_depth == 12 and cap.manifest.camera.bit_depth == 12 and r.view == 4
        np.testing.assert_allclose(r.frame_times_s, 0.0095 + np.arange(12) / 1000.0)
        assert r.sample_rate_hz == pytest.approx(20_000.0)
        assert r.channel("force").max() == pytest.approx(100.0, rel=1e-3)
        assert np.abs(r.channel("acc1")).max() == pytest.approx(9.80665, rel=1e-3)
        assert r.channel_info("acc1").position_m == [0.1, 0.2, 0.3]
        assert r.trigger.trigger_time_s == pytest.approx(0.01)


def test_csv_with_nan_leaves_nothing(tmp_path):
    _write_sequence(tmp_path / "seq", 3)
    _write_csv(tmp_path / "daq.csv", 200, 20_000.0, bad="nan")
    out = tmp_path / "cap"
    with pytest.raises(InputError, match=r"daq\.csv.*(NaN|nan)"):
        import_capture(_rig(tmp_path), out)
    assert _nothing_left(out)


def test_missing_column_is_named(tmp_path):
    _write_sequence(tmp_path / "seq", 3)
    _write_csv(tmp_path / "daq.csv", 200, 20_000.0)
    out = tmp_path / "cap"
    extra = '[[channels]]\nname = "acc2"\nkind = "acceleration"\n'
    with pytest.raises(InputError, match=r"daq\.csv.*acc2"):
        import_capture(_rig(tmp_path, extra), out)
    assert _nothing_left(out)


def test_unit_that_does_not_fit_the_kind(tmp_path):
    _write_sequence(tmp_path / "seq", 3)
    _write_csv(tmp_path / "daq.csv", 200, 20_000.0)
    rig = _rig(tmp_path)
    rig.write_text(rig.read_text().replace('column = "hammer"', 'column = "hammer"\nunit = "g"', 1))
    with pytest.raises(InputError, match=r"hammer.*m/s\^2.*force"):
        import_capture(rig, tmp_path / "cap")


def test_rig_field_errors_name_the_path(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "x"\n[[takes]]\nvideo = "a.npy"\nfps = "fast"\n')
    with pytest.raises(InputError, match=r"rig\.toml\.takes\[0\]\.fps: expected a number"):
        import_capture(rig, tmp_path / "cap")
    rig.write_text('name = "x"\n[[channels]]\nname = "f"\nkind = "strain"\n[[takes]]\nsignals = "a.csv"\n')
    with pytest.raises(InputError, match=r"channels\[0\]\.kind"):
        import_capture(rig, tmp_path / "cap")


def test_existing_capture_is_not_overwritten(tmp_path):
    (tmp_path / "cap").mkdir()
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "x"\n[[takes]]\nvideo = "a.npy"\n')
    with pytest.raises(InputError, match="exists already"):
        import_capture(rig, tmp_path / "cap")


def test_two_takes_with_seven_digit_time_stamps_share_one_rate(tmp_path):
    """A lab's export: a `time_s` column printed to 7 significant digits. The two takes' rates read 1e-7 apart
    (20479.99808 against 20479.9994 Hz in the issue's files) and are one clock, within RATE_TOLERANCE."""
    fs = 20_480.0
    for name, n in (("a.csv", 4096), ("b.csv", 3000)):
        t = np.arange(n) / fs
        force = np.exp(-(((t - 0.01) / 0.0005) ** 2)) * 100.0
        (tmp_path / name).write_text("time_s,hammer [N],acc1 [g]\n" + "".join(
            f"{a:.7g},{b:.6f},{np.sin(2 * np.pi * 80 * a):.6f}\n" for a, b in zip(t, force)))
    rig = tmp_path / "rig.toml"
    rig.write_text(
        'name = "lab"\n'
        '[[channels]]\nname = "force"\nkind = "force"\ncolumn = "hammer"\n'
        '[[channels]]\nname = "acc1"\nkind = "acceleration"\n'
        '[[takes]]\nname = "a"\nsignals = "a.csv"\n[[takes]]\nname = "b"\nsignals = "b.csv"\n')
    cap = import_capture(rig, tmp_path / "cap")
    assert cap.manifest.daq_sample_rate_hz == pytest.approx(fs, rel=1e-6)
    with cap.open_take("b") as r:
        assert r.n_samples == 3000 and r.channel("force").max() == pytest.approx(100.0, rel=1e-3)
    # Rates a real difference apart are still refused, naming the rig.
    (tmp_path / "b.csv").write_text("time_s,hammer [N],acc1 [g]\n" + "".join(
        f"{k / 20_000.0:.7g},{k % 3},{k % 5}\n" for k in range(3000)))
    with pytest.raises(InputError, match=r"rig\.toml: takes: signal files disagree on the sample rate"):
        import_capture(rig, tmp_path / "cap2")
    assert not (tmp_path / "cap2").exists()


def test_the_rig_names_an_image_sequence_trigger_frame(tmp_path):
    """An image sequence has no header: the rig's `trigger_frame` says which file frame the camera triggered on.
    It becomes camera frame 0, as sync reads the counter, and the frames' DAQ times follow from it."""
    _write_sequence(tmp_path / "seq", 12)
    _write_csv(tmp_path / "daq.csv", 2000, 20_000.0)
    rig = _rig(tmp_path)
    rig.write_text(rig.read_text() + "trigger_frame = 3\n")
    cap = import_capture(rig, tmp_path / "cap")
    with cap.open_take("hit") as r:
        assert r.trigger.camera_trigger_frame == 3
        np.testing.assert_array_equal(r.frame_counter, np.arange(12) - 3)
        np.testing.assert_allclose(r.frame_times_s, 0.0095 + (np.arange(12) - 3) / 1000.0)
    for value, message in (("12", r"expected a frame index from 0 to 11; got 12"), ("-1", "got -1")):
        rig.write_text(rig.read_text().rsplit("trigger_frame", 1)[0] + f"trigger_frame = {value}\n")
        with pytest.raises(InputError, match=message) as err:
            import_capture(rig, tmp_path / f"bad{value}")
        assert err.value.source.endswith("takes[0].trigger_frame")
        assert not (tmp_path / f"bad{value}").exists()


def test_a_slow_motion_file_gets_its_true_rate_from_the_rig(tmp_path):
    """A clip filmed at 600 fps and stored for playback at 29.97 fps: fps = 600 is refused (the file says
    otherwise, and the error says what to write), recorded_fps = 600 imports it at 600 fps."""
    path = tmp_path / "slowmo.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 29.97, (64, 48))
    for i in range(8):
        writer.write(np.full((48, 64, 3), 20 * i, np.uint8))
    writer.release()
    _write_csv(tmp_path / "daq.csv", 2000, 20_000.0)
    rig = tmp_path / "rig.toml"
    base = ('name = "phone"\n[[channels]]\nname = "force"\nkind = "force"\ncolumn = "hammer"\n'
            '[[channels]]\nname = "acc1"\nkind = "acceleration"\n'
            '[[takes]]\nname = "hit"\nvideo = "slowmo.avi"\nsignals = "daq.csv"\ncamera_trigger_time_s = 0.01\n')
    rig.write_text(base + "fps = 600\n")
    with pytest.raises(InputError, match=r"says 29\.97 fps, but fps=600 was given .*recorded_fps = 600"):
        import_capture(rig, tmp_path / "bad")
    rig.write_text(base + "recorded_fps = 600\n")
    cap = import_capture(rig, tmp_path / "cap")
    assert cap.manifest.camera.fps == 600.0
    with cap.open_take("hit") as r:
        assert r.fps == 600.0 and r.n_frames == 8
        np.testing.assert_allclose(r.frame_times_s, 0.01 + np.arange(8) / 600.0)
    rig.write_text(base + "recorded_fps = 600\nfps = 600\n")
    with pytest.raises(InputError, match="not both") as err:
        import_capture(rig, tmp_path / "both")
    assert err.value.source.endswith("takes[0].recorded_fps")


def test_a_png_and_csv_bundle_imports_with_no_edits_and_qc_judges_its_takes(tmp_path):
    """A plain bundle as a lab exports it: PNG frames, and a CSV whose time column is `time_s` printed to 7
    significant digits. It imports as it is; qc then accepts the clean hit and rejects the double hit, and the
    stages select by that verdict."""
    from odsplat.acquisition import run_qc

    frames = _write_sequence(tmp_path / "seq", 12)
    fs = 20_480.0
    for name, hits in (("daq.csv", (0.01,)), ("double.csv", (0.01, 0.03))):
        t = np.arange(4096) / fs
        force = sum(np.exp(-(((t - t0) / 0.0005) ** 2)) * 100.0 for t0 in hits)
        (tmp_path / name).write_text("time_s,hammer [N],acc1 [g]\n" + "".join(
            f"{a:.7g},{b:.6f},{np.sin(2 * np.pi * 80 * a):.6f}\n" for a, b in zip(t, force)))
    rig = _rig(tmp_path)
    rig.write_text(rig.read_text() + '[[takes]]\nname = "again"\nsignals = "double.csv"\npretrigger_samples = 200\n')
    cap = import_capture(rig, tmp_path / "cap")
    with cap.open_take("hit") as r:
        np.testing.assert_array_equal(r.read_frames(), frames)
        assert r.sample_rate_hz == pytest.approx(fs, rel=1e-6)
    assert [t.qc for t in cap.manifest.takes] == ["unchecked", "unchecked"] and cap.select_takes() == []
    report = run_qc(cap)
    verdicts = {t.name: (t.status, t.reasons) for t in report.takes}
    assert verdicts == {"hit": ("accepted", ()), "again": ("rejected", ("double_hit",))}
    assert [t.name for t in Capture.open(cap.root).select_takes()] == ["hit"]
    assert len(Capture.open(cap.root).select_takes("all")) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cap", "daq.csv", "double.csv", "rig.toml", "seq"]


def test_a_phantom_cine_imports_with_its_header(shared_data, tmp_path):
    """pyidi's .cine sample: 235 frames of 256x32 at 100 fps, packed 10-bit read as linear 12-bit; FirstImageNo 0
    makes the first frame the trigger frame, counter 0."""
    from cine_reader import Cine

    rig = tmp_path / "rig.toml"
    rig.write_text('name = "phantom"\n[[takes]]\nname = "cine"\nvideo = "pyidi-samples/data_small_cine.cine"\n'
                   'camera_trigger_time_s = 0.02\n')
    cap = import_capture(rig, tmp_path / "cap", data_dir=shared_data)
    camera = cap.manifest.camera
    assert (camera.width_px, camera.height_px, camera.fps, camera.bit_depth) == (256, 32, 100.0, 12)
    assert camera.model == "Phantom, serial 34497"
    reference = Cine(shared_data / "pyidi-samples" / "data_small_cine.cine", keep_annotations=False)
    with cap.open_take("cine") as r:
        assert (r.n_frames, r.frame_shape, r.frames.dtype, r.bit_depth) == (235, (32, 256), np.uint16, 12)
        assert r.trigger.camera_trigger_frame == 0
        np.testing.assert_array_equal(r.frame_counter, np.arange(235))
        np.testing.assert_allclose(r.frame_times_s, 0.02 + np.arange(235) / 100.0)
        frames = np.concatenate(list(r.iter_frames(64)))
    for i in (0, 100, 234):
        reference.load_frame(i)
        np.testing.assert_array_equal(frames[i], reference.frame)


@pytest.mark.parametrize("peak, detected", [(255, 8), (256, 10), (1023, 10), (1024, 12), (4095, 12), (4096, 14),
                                            (16384, 16), (65535, 16)])
def test_bit_depth_is_detected_from_the_data(tmp_path, caplog, peak, detected):
    frames = np.zeros((5, 4, 6), np.uint16)
    frames[3, 2, 1] = peak
    np.save(tmp_path / "take.npy", frames)
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "depth"\n[[takes]]\nname = "t"\nvideo = "take.npy"\nfps = 100\n')
    with caplog.at_level("INFO", logger="odsplat.importer"):
        cap = import_capture(rig, tmp_path / "cap")
    assert cap.manifest.camera.bit_depth == detected
    with cap.open_take("t") as r:
        assert r.bit_depth == detected
    assert f"take.npy: {detected}-bit data detected in 16-bit samples (the largest value is {peak})" in caplog.text


def test_declared_bit_depth_is_recorded_and_checked(tmp_path):
    frames = np.zeros((70, 4, 6), np.uint16)
    frames[:, 0, 0] = 1000
    np.save(tmp_path / "take.npy", frames)
    rig = tmp_path / "rig.toml"
    base = 'name = "depth"\n[[takes]]\nname = "t"\nvideo = "take.npy"\nfps = 100\n'
    rig.write_text(base + "[camera]\nbit_depth = 12\n")
    cap = import_capture(rig, tmp_path / "cap12")      # 1000 would be detected as 10 bits; the rig says 12
    assert cap.manifest.camera.bit_depth == 12
    with cap.open_take("t") as r:
        assert r.bit_depth == 12
    frames[66, 1, 2] = 5000                            # in the second chunk of 64: refused while writing
    np.save(tmp_path / "take.npy", frames)
    with pytest.raises(InputError, match="12, but frame 66 of take.npy holds 5000, more than 4095") as err:
        import_capture(rig, tmp_path / "bad")
    assert err.value.source == f"{rig}: camera.bit_depth" and _nothing_left(tmp_path / "bad")
    for value, message in (("11", "expected one of 8, 10, 12, 14, 16; got 11"), ('"12"', "expected")):
        rig.write_text(base + f"[camera]\nbit_depth = {value}\n")
        with pytest.raises(InputError, match=message):
            import_capture(rig, tmp_path / "bad")
        assert _nothing_left(tmp_path / "bad")
    np.save(tmp_path / "take.npy", np.zeros((2, 4, 6), np.uint8))
    rig.write_text(base + "[camera]\nbit_depth = 12\n")
    with pytest.raises(InputError, match=r"12, but take.npy holds 8-bit samples \(uint8\)"):
        import_capture(rig, tmp_path / "bad")


def test_the_rig_names_the_time_column_or_declares_the_rate(tmp_path):
    """A lab's own heading for time (`Zeit [ms]`, not first) is named in the rig; a file with no time column
    takes the declared rate; a declared rate the time column contradicts is refused naming the field."""
    fs = 10_000.0
    t = np.arange(2000) / fs
    force = np.exp(-(((t - 0.01) / 0.0005) ** 2)) * 50.0
    (tmp_path / "zeit.csv").write_text("hammer [N];Zeit [ms];acc1 [g]\n" + "".join(
        f"{b:.6f};{1e3 * a:.4f};{np.sin(2 * np.pi * 80 * a):.6f}\n" for a, b in zip(t, force)))
    (tmp_path / "bare.csv").write_text("hammer [N],acc1 [g]\n" + "".join(
        f"{b:.6f},{np.sin(2 * np.pi * 80 * a):.6f}\n" for a, b in zip(t, force)))
    rig = tmp_path / "rig.toml"
    body = ('name = "lab"\n[[channels]]\nname = "force"\nkind = "force"\ncolumn = "hammer"\n'
            '[[channels]]\nname = "acc1"\nkind = "acceleration"\n')
    rig.write_text(body + '[[takes]]\nname = "a"\nsignals = "zeit.csv"\ntime_column = "Zeit"\n'
                   '[[takes]]\nname = "b"\nsignals = "bare.csv"\nsample_rate_hz = 10000\n')
    cap = import_capture(rig, tmp_path / "cap")
    assert cap.manifest.daq_sample_rate_hz == fs
    for name in ("a", "b"):
        with cap.open_take(name) as r:
            assert r.n_samples == 2000 and r.channel("force").max() == pytest.approx(50.0, rel=1e-3)
    rig.write_text(body + '[[takes]]\nname = "a"\nsignals = "zeit.csv"\ntime_column = "Zeit"\n'
                   'sample_rate_hz = 12000\n')
    with pytest.raises(InputError, match=r"zeit\.csv: sample_rate_hz: the file's time axis gives 10000 Hz, "
                                         r"not the 12000 Hz declared"):
        import_capture(rig, tmp_path / "bad")
    rig.write_text(body + '[[takes]]\nname = "b"\nsignals = "bare.csv"\n')
    with pytest.raises(InputError, match=r"bare\.csv: first column must be time .* or declare sample_rate_hz"):
        import_capture(rig, tmp_path / "bad")
    assert not (tmp_path / "bad").exists()
