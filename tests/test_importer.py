"""`odsplat import`: real recordings into a capture; bad input stops with one line and leaves nothing."""
from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from odsplat.spine.errors import InputError
from odsplat.spine.importer import import_capture
from odsplat.spine.store import Capture

REPO = Path(__file__).resolve().parents[1]


def _nothing_left(out: Path) -> bool:
    return not out.exists() and not list(out.parent.glob(f".{out.name}.importing-*"))


def test_ladisk_example_rig(shared_data, tmp_path):
    out = tmp_path / "beam"
    cap = import_capture(REPO / "odsplat" / "examples" / "ladisk-beam.toml", out, data_dir=shared_data)
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
    with caplog.at_level("INFO", logger="odsplat.spine.importer"):
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


# ------------------------------------------------------------------ hardening (issue 29): hostile and broken inputs

LADISK = "ladisk-imaging-tutorial"
CHANNELS = ('[[channels]]\nname = "force"\nkind = "force"\ncolumn = "Force (Trigger)"\n'
            '[[channels]]\nname = "acc"\nkind = "acceleration"\ncolumn = "Acceleration (Trigger)"\n')


def _listing(folder: Path) -> set[Path]:
    return {p.relative_to(folder) for p in folder.rglob("*")}


def _refused(rig: Path, out: Path, match: str, *, data_dir: Path | None = None) -> InputError:
    """The import is refused with one line matching `match`, and nothing is written anywhere under rig's folder."""
    before = _listing(rig.parent)
    with pytest.raises(InputError, match=match) as err:
        import_capture(rig, out, data_dir=data_dir)
    assert "\n" not in str(err.value)
    assert _nothing_left(out) and _listing(rig.parent) == before
    return err.value


def _npy_rig(tmp_path: Path, take: str = "", top: str = "") -> Path:
    np.save(tmp_path / "x.npy", np.arange(3 * 4 * 6, dtype=np.uint8).reshape(3, 4, 6))
    rig = tmp_path / "rig.toml"
    rig.write_text(f'name = "h"\n{top}[[takes]]\nvideo = "x.npy"\nfps = 100\n{take}')
    return rig


@pytest.mark.parametrize("name", ["../../x", "/tmp/x", "a/b", "..", ".", ".hidden", "a\\\\b", "a b", "x" * 101])
def test_a_take_name_that_would_leave_the_capture_is_refused(tmp_path, name):
    data = tmp_path / "data"
    data.mkdir()
    rig = _npy_rig(data, f'name = "{name}"\n')
    before = _listing(tmp_path)
    with pytest.raises(InputError, match=r"rig\.toml: takes\[0\]\.name: ") as err:
        import_capture(rig, data / "cap")
    assert "\n" not in str(err.value) and _listing(tmp_path) == before


def test_the_store_checks_take_names_too(tmp_path):
    from odsplat.spine.manifest import Manifest

    cap = Capture.create(tmp_path / "cap", Manifest(name="x"))
    for name in ("../x", "a/b", "a\0b", "x" * 300):
        with pytest.raises(InputError, match="take name"):
            cap.new_take(name)
    assert _listing(tmp_path) == {Path("cap"), *(Path("cap") / p for p in _listing(tmp_path / "cap"))}
    assert sorted(p.name for p in (tmp_path / "cap" / "takes").iterdir()) == []


@pytest.mark.parametrize("field, value", [
    ("video", "../outside.npy"), ("video", "{outside}"), ("signals", "../../../../../../etc/passwd"),
    ("static", "../../../../../../etc/passwd"), ("static", "../*.npy"), ("static", "{outside}"),
    ("video", "link.npy"),
])
def test_a_rig_path_that_leads_outside_the_data_folder_is_refused(tmp_path, field, value):
    data = tmp_path / "data"
    data.mkdir()
    np.save(tmp_path / "outside.npy", np.zeros((3, 4, 6), np.uint8))
    (data / "link.npy").symlink_to(tmp_path / "outside.npy")
    rig = _npy_rig(data)
    value = value.format(outside=tmp_path / "outside.npy")
    if field == "static":
        rig.write_text(f'static = ["{value}"]\n' + rig.read_text())
    elif field == "signals":
        rig.write_text(rig.read_text() + f'signals = "{value}"\n')
    else:
        rig.write_text(rig.read_text().replace('"x.npy"', f'"{value}"'))
    field = "static[0]" if field == "static" else f"takes[0].{field}"
    before = _listing(tmp_path)
    with pytest.raises(InputError, match=r"leads outside") as err:
        import_capture(rig, data / "cap")
    assert err.value.source == f"{rig}: {field}" and _listing(tmp_path) == before


def test_static_photos_are_copied_from_the_data_folder_only(tmp_path):
    data = tmp_path / "data"
    (data / "photos").mkdir(parents=True)
    (data / "photos" / "front.png").write_bytes(b"png")
    rig = _npy_rig(data, top='static = ["photos/*.png"]\n')
    cap = import_capture(rig, tmp_path / "cap", data_dir=data)
    assert sorted(p.name for p in (cap.root / "static").iterdir()) == ["front.png"]
    rig.write_text(rig.read_text().replace("photos/*.png", "photos/*.jpg"))
    _refused(rig, tmp_path / "cap2", r"static\[0\]: 'photos/\*\.jpg' matches no file", data_dir=data)
    rig.write_text(rig.read_text().replace("photos/*.jpg", "photos"))
    _refused(rig, tmp_path / "cap2", r"photos: is a folder", data_dir=data)


def _edit_cih(shared_data: Path, dest: Path, field: str, value: str, sample: str = f"{LADISK}/focus.cih") -> Path:
    cih = dest / "cam.cih"
    text = (shared_data / sample).read_bytes().decode("latin-1")
    start = text.index(f"\n{field} :") + 1
    end = text.index("\n", start)
    cih.write_bytes((text[:start] + f"{field} : {value}" + text[end:]).encode("latin-1"))
    shutil.copyfile((shared_data / sample).with_suffix(".mraw"), dest / "cam.mraw")
    return cih


@pytest.mark.parametrize("field, value, match", [
    ("Start Frame", "-99999999999999999999", r"'Start Frame' = '-99999999999999999999' lies beyond"),
    ("Record Rate(fps)", "nan", r"Record Rate\(fps\): nan is not a frame rate from 0\.001 to 1e\+08 fps"),
    ("Record Rate(fps)", "inf", "inf is not a frame rate"),
    ("Record Rate(fps)", "1e-300", "1e-300 is not a frame rate"),
    ("Record Rate(fps)", "1e308", "1e\\+308 is not a frame rate"),
    ("EffectiveBit Depth", "0", r"'EffectiveBit Depth' = 0; expected 8 to 16 bits"),
    ("EffectiveBit Depth", "-4", "= -4; expected 8 to 16"),
    ("EffectiveBit Depth", "4", "= 4; expected 8 to 16"),
])
def test_a_garbled_photron_header_field_is_refused(shared_data, tmp_path, field, value, match):
    _edit_cih(shared_data, tmp_path, field, value)
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "h"\n[[takes]]\nvideo = "cam.cih"\n')
    assert _refused(rig, tmp_path / "cap", match).source.startswith(str(tmp_path / "cam.cih"))


def test_a_12_bit_mraw_holding_more_than_12_bits_is_refused(shared_data, tmp_path):
    """beam: 12-bit data in 16-bit words (EffectiveBit 12); a sample of 5000 cannot be 12-bit data."""
    src = shared_data / "pymraw-samples" / "beam.cihx"
    shutil.copyfile(src, tmp_path / "beam.cihx")
    frames = np.fromfile(src.with_suffix(".mraw"), dtype="<u2").reshape(4, 80, 1024)
    frames[2, 10, 20] = 5000
    frames.tofile(tmp_path / "beam.mraw")
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "h"\n[[takes]]\nvideo = "beam.cihx"\n')
    _refused(rig, tmp_path / "cap", r"beam\.cihx: its header says 12-bit data, but frame 2 holds 5000, more than 4095")


def _save_npy_header(path: Path, header: bytes) -> None:
    np.save(path, np.zeros((3, 4, 6), np.uint8))
    data = bytearray(path.read_bytes())
    data[10:10 + len(header)] = header
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("case, match", [
    ("zero_height", r"x\.npy: holds 8 frames of 64x0 pixels; nothing to import"),
    ("no_frames", r"x\.npy: holds 0 frames"),
    ("garbled_header", r"x\.npy: cannot be read as a plain \.npy array"),
    ("empty", r"x\.npy: cannot be read as a plain \.npy array"),
    ("npz", r"x\.npy: cannot be read as a plain \.npy array .*magic"),
    ("zero_byte_png", r"seq/img_1\.png: cannot be decoded as an image \(0 bytes\)"),
])
def test_a_broken_array_or_image_is_refused(tmp_path, case, match):
    rig = _npy_rig(tmp_path)
    npy = tmp_path / "x.npy"
    if case == "zero_height":
        np.save(npy, np.zeros((8, 0, 64), np.uint8))
    elif case == "no_frames":
        np.save(npy, np.zeros((0, 4, 6), np.uint8))
    elif case == "garbled_header":
        _save_npy_header(npy, b"{'descr': '|u1', 'fortran_order': False, 'shape': ((((((")
    elif case == "empty":
        npy.write_bytes(b"")
    elif case == "npz":
        np.savez(tmp_path / "y.npz", a=np.zeros((3, 4, 6), np.uint8))
        (tmp_path / "y.npz").rename(npy)
    else:
        _write_sequence(tmp_path / "seq", 3)
        (tmp_path / "seq" / "img_1.png").write_bytes(b"")
        rig.write_text(rig.read_text().replace('"x.npy"', '"seq"'))
    _refused(rig, tmp_path / "cap", match)


@pytest.mark.parametrize("content, match", [
    (b'name = "caf\xe9"\n', r"rig\.toml: not TOML: not UTF-8 text \(byte 11 is b'\\xe9'\)"),
    (bytes(range(256)), r"rig\.toml: not TOML: not UTF-8 text"),
    ('name = "h"\n[[takes]]\nname = "a\\u0000b"\nvideo = "x.npy"\nfps = 100\n', r"takes\[0\]\.name: holds a NUL"),
    (f'name = "h"\n[[takes]]\nname = "{"n" * 300}"\nvideo = "x.npy"\nfps = 100\n',
     r"rig\.toml: takes\[0\]\.name: 300 characters; a name has at most 100"),
])
def test_a_rig_file_that_is_not_text_or_names_badly_is_refused(tmp_path, content, match):
    rig = _npy_rig(tmp_path)
    rig.write_bytes(content if isinstance(content, bytes) else content.encode())
    _refused(rig, tmp_path / "cap", match)


def test_a_folder_as_the_rig_or_an_output_under_a_file_is_refused(tmp_path):
    rig = _npy_rig(tmp_path)
    (tmp_path / "folder.toml").mkdir()
    _refused(tmp_path / "folder.toml", tmp_path / "cap", r"folder\.toml: is a folder; expected a TOML file")
    (tmp_path / "file").write_text("x")
    _refused(rig, tmp_path / "file" / "cap", r"file/cap: its folder .*file is not a folder")
    _refused(rig, tmp_path / "no" / "cap", r"no/cap: its folder .*no does not exist")


def _cli(*args: str, timeout: float = 60) -> tuple[int, str]:
    import subprocess
    import sys

    proc = subprocess.run([sys.executable, "-m", "odsplat", "import", *args], capture_output=True, text=True,
                          timeout=timeout)
    return proc.returncode, proc.stderr


def test_the_cli_refuses_a_fifo_header_with_one_line_and_status_2(shared_data, tmp_path):
    """A FIFO named as the .cih would block the read for ever: it is refused before it is opened."""
    import os

    os.mkfifo(tmp_path / "cam.cih")
    shutil.copyfile(shared_data / LADISK / "focus.mraw", tmp_path / "cam.mraw")
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "h"\n[[takes]]\nvideo = "cam.cih"\n')
    status, stderr = _cli(str(rig), "-o", str(tmp_path / "cap"))
    assert status == 2 and stderr.strip().count("\n") == 0 and "Traceback" not in stderr
    assert "cam.cih: is a FIFO; expected a recording" in stderr and _nothing_left(tmp_path / "cap")


def _lvm_rig(shared_data: Path, tmp_path: Path, edit) -> Path:
    lines = (shared_data / LADISK / "acceleration.lvm").read_text().split("\n")
    (tmp_path / "a.lvm").write_text("\n".join(edit(lines)))
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "h"\n' + CHANNELS + '[[takes]]\nsignals = "a.lvm"\n')
    return rig


def _set(lines: list[str], tag: str, value: str) -> list[str]:
    return [f"{tag}\t{value}\t{value}\t" if line.startswith(tag + "\t") else line for line in lines]


@pytest.mark.parametrize("edit, match", [
    (lambda lines: lines[:20050], r"a\.lvm: segment 1: truncated: 20027 rows, but its header declares 50030 Samples"),
    (lambda lines: lines[:23], "truncated: 0 rows"),
    (lambda lines: _set(lines, "X0", "NaN"), r"segment 1: X0 \['NaN', 'NaN', ''\] is not a finite number"),
    (lambda lines: _set(lines, "Delta_X", "1,0E-300"), r"a\.lvm: Delta_X, X0: 1e\+300 is not a sample rate from 1 to "
                                                        r"1e\+09 Hz"),
    (lambda lines: _set(lines, "Delta_X", "inf"), r"Delta_X \['inf', 'inf', ''\] is not a finite number"),
    (lambda lines: lines[:30] + [lines[30] + "\t1,0\t2,0"] + lines[31:],
     r"a\.lvm: line 31 has 5 fields, more than the 4 columns of the heading: a ragged row"),
])
def test_a_damaged_lvm_is_refused(shared_data, tmp_path, edit, match):
    _refused(_lvm_rig(shared_data, tmp_path, edit), tmp_path / "cap", match)


def test_ragged_or_overflowing_csv_and_non_finite_uff_are_refused(shared_data, tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text('name = "h"\n[[channels]]\nname = "f"\nkind = "force"\n[[takes]]\nsignals = "a.csv"\n')
    (tmp_path / "a.csv").write_text("time [s],f [N]\n0,1\n0.1,2,3\n0.2,3\n")
    _refused(rig, tmp_path / "cap", r"a\.csv: line 3 has 3 fields, more than the 2 columns")
    (tmp_path / "a.csv").write_text("time [s],f [N],\n0,1,\n0.1,2,\n0.2,3,\n")   # trailing delimiters are no data
    import_capture(rig, tmp_path / "ok")
    (tmp_path / "a.csv").write_text("time [s],f [kN]\n0,1\n0.1,1e38\n0.2,3\n")
    _refused(rig, tmp_path / "cap", r"a\.csv: column 'f': sample 1 is 1e\+38 kN, beyond float32 once converted to N")
    uff = (shared_data / "pyuff-samples" / "time-history-not-all-columns-filled.uff").read_bytes()
    (tmp_path / "a.uff").write_bytes(uff.replace(b"-3.56616E+00", b"         NaN", 1))
    rig.write_text('name = "h"\n[[channels]]\nname = "a"\nkind = "acceleration"\ncolumn = "1x : m/s²"\n'
                   '[[takes]]\nsignals = "a.uff"\n')
    _refused(rig, tmp_path / "cap", r"a\.uff: column '1x : m/s²': sample 1 is nan m/s², not a finite number")


@pytest.mark.parametrize("rig_text, match", [
    ('[[takes]]\nvideo = "x.npy"\nfps = nan\n', r"takes\[0\]\.fps: expected a finite number; got nan"),
    ('[[takes]]\nvideo = "x.npy"\nfps = inf\n', r"takes\[0\]\.fps: expected a finite number; got inf"),
    ('[[takes]]\nvideo = "x.npy"\nfps = 1e-300\n', r"takes\[0\]\.fps: 1e-300 is not a frame rate"),
    ('[[takes]]\nvideo = "x.npy"\nfps = 1e308\n', r"takes\[0\]\.fps: 1e\+308 is not a frame rate"),
    ('[[takes]]\nvideo = "x.npy"\n', r"takes\[0\]\.fps: x\.npy holds no frame rate; give the take's fps"),
    ('[[takes]]\nvideo = ""\nsignals = "a.csv"\n', r"takes\[0\]\.video: is empty"),
    ('[[takes]]\nvideo = "x.npy"\nfps = 100\nview = -3\n', r"takes\[0\]\.view: expected 0 or more; got -3"),
    ('[[takes]]\nsignals = "a.csv"\npretrigger_samples = -500\n', r"pretrigger_samples: expected 0 or more"),
    ('[[takes]]\nsignals = "a.csv"\npretrigger_samples = 1000000\n',
     r"takes\[0\]\.pretrigger_samples: 1000000, but a\.csv holds 200 samples"),
    ('[[takes]]\nvideo = "x.npy"\nfps = 100\npretrigger_samples = 3\n', "pretrigger samples need the take's signals"),
    ('[camera.intrinsics]\nfx_px = nan\nfy_px = 1\ncx_px = 0\ncy_px = 0\n[[takes]]\nvideo = "x.npy"\nfps = 100\n',
     r"camera\.intrinsics\.fx_px: expected a finite number; got nan"),
    ('[camera.intrinsics]\nfx_px = -1\nfy_px = 1\ncx_px = 0\ncy_px = 0\n[[takes]]\nvideo = "x.npy"\nfps = 100\n',
     r"camera\.intrinsics\.fx_px: expected a positive number; got -1"),
    ('[tags]\nsize_m = -0.03\n[[takes]]\nvideo = "x.npy"\nfps = 100\n', r"tags\.size_m: expected a positive number"),
    ('[tags]\nsize_m = 0.03\n[[tags.tags]]\nid = 0\ncorners_m = [[1, 2]]\n[[takes]]\nvideo = "x.npy"\nfps = 100\n',
     r"tags\.tags\[0\]\.corners_m: expected 4 corners of 3 numbers"),
    ('[[takes]]\nsignals = "a.csv"\n', None),   # with the channel below: a NaN position, a zero direction
])
def test_rig_values_are_checked(tmp_path, rig_text, match):
    _write_csv(tmp_path / "a.csv", 200, 20_000.0)
    rig = _npy_rig(tmp_path)
    channels = '[[channels]]\nname = "force"\nkind = "force"\ncolumn = "hammer"\n'
    if match is None:
        for acc, match in (('position_m = [0, nan, 0]', r"channels\[0\]\.position_m\[1\]: expected a finite number"),
                           ('direction = [0, 0, 0]', r"channels\[0\]\.direction: expected a non-zero direction")):
            rig.write_text(f'name = "h"\n{channels}{acc}\n{rig_text}')
            _refused(rig, tmp_path / "cap", match)
        return
    rig.write_text(f'name = "h"\n{channels}{rig_text}')
    _refused(rig, tmp_path / "cap", match)


def test_a_killed_import_leaves_a_temporary_that_the_next_import_removes(shared_data, tmp_path):
    """SIGKILL an import at a random point (seeded) while it writes; the rerun succeeds and leaves no temporary."""
    import os
    import random
    import signal
    import subprocess
    import sys
    import time

    rig = tmp_path / "rig.toml"
    rig.write_text('name = "k"\n' + CHANNELS + "".join(
        f'[[takes]]\nname = "t{i}"\nsignals = "{LADISK}/acceleration.lvm"\n'
        f'[[takes]]\nname = "v{i}"\nvideo = "pyidi-samples/data_showcase.cih"\n' for i in range(8)))
    out = tmp_path / "cap"
    proc = subprocess.Popen([sys.executable, "-m", "odsplat", "import", str(rig), "-o", str(out), "--data",
                             str(shared_data)], stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".cap.importing-*")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.005)
    time.sleep(random.Random(29).uniform(0.0, 0.2))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read()
    left = list(tmp_path.glob(".cap.importing-*"))
    assert len(left) == 1 and not out.exists()   # killed while building: the temporary is there, OUT is not
    cap = import_capture(rig, out, data_dir=shared_data)
    assert len(cap.manifest.takes) == 16 and not list(tmp_path.glob(".*importing*"))


def test_only_temporaries_of_dead_imports_on_this_host_are_removed(tmp_path):
    import os
    import socket
    import subprocess
    import sys

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    host = socket.gethostname()
    names = {"dead": f".a.importing-{host}-{dead.pid}", "dead_old_style": f".b.importing-{dead.pid}",
             "live": f".c.importing-{host}-{os.getppid()}", "other_host": f".d.importing-elsewhere-{dead.pid}"}
    for name in names.values():
        (tmp_path / name / "takes").mkdir(parents=True)
    import_capture(_npy_rig(tmp_path), tmp_path / "cap")
    left = {p.name for p in tmp_path.glob(".*")}
    assert left == {names["live"], names["other_host"]}
