"""The Photron driver's pure parts (parameter mapping, recording window, unpacking, names) and its
refusal to start without the SDK. Nothing here calls PDCLIB: no camera, no SDK, no fake of either."""
from __future__ import annotations

import ctypes
import ctypes.util
import inspect
import os
import re
import time

import numpy as np
import pyMRAW
import pytest

from odsplat.acquisition import photron
from odsplat.acquisition.camera import CameraTimeout, TriggerSettings
from odsplat.acquisition.photron import (
    LIBRARY_ENV,
    PDC,
    SIGNATURES,
    PdcError,
    PhotronCamera,
    RecordingWindow,
    choose_record_rate,
    choose_shutter,
    error_message,
    frame_bytes,
    ip_to_pdc,
    plan_trigger,
    select_window,
    status_name,
    unpack_12bit,
    unpack_frame,
)
from odsplat.spine.errors import InputError

# -------------------------------------------------------------------- no SDK

def test_constructing_without_the_sdk_names_the_library(monkeypatch, tmp_path):
    monkeypatch.delenv(LIBRARY_ENV, raising=False)
    if ctypes.util.find_library("PDCLIB"):
        pytest.skip("a PDCLIB is installed here; the default search would find it")
    with pytest.raises(InputError, match=r"^PDCLIB \(Photron SDK\): not found; tried (lib)?PDCLIB\.(so|dll)") as err:
        PhotronCamera("192.168.0.10")
    assert LIBRARY_ENV in str(err.value)

    from_env = tmp_path / "sdk" / "libPDCLIB.so"
    monkeypatch.setenv(LIBRARY_ENV, str(from_env))
    with pytest.raises(InputError, match=f"tried {re.escape(str(from_env))} ") as err:
        PhotronCamera("192.168.0.10")
    assert "check the path" in str(err.value)

    given = tmp_path / "elsewhere" / "PDCLIB.dll"
    with pytest.raises(InputError, match=f"tried {re.escape(str(given))} "):
        PhotronCamera("192.168.0.10", library=given)


def test_arguments_are_checked_before_the_sdk_is_looked_for():
    with pytest.raises(InputError, match="PhotronCamera.ip: expected an IPv4 address"):
        PhotronCamera("192.168.0.300")
    with pytest.raises(InputError, match="PhotronCamera.transfer_bits"):
        PhotronCamera("192.168.0.10", transfer_bits=10)


def test_every_sdk_function_the_driver_calls_has_a_signature():
    called = set(re.findall(r'"(PDC_\w+)"', inspect.getsource(photron.PhotronCamera)))
    assert called and called <= set(SIGNATURES), called - set(SIGNATURES)
    for argtypes in SIGNATURES.values():
        ctypes.CFUNCTYPE(ctypes.c_ulong, *argtypes, ctypes.POINTER(ctypes.c_ulong))  # valid ctypes types


def test_ip_addresses_in_host_order():
    assert ip_to_pdc("192.168.0.10") == 0xC0A8000A  # the value Photron's samples put in IPList[0]
    assert ip_to_pdc(" 10.0.0.1 ") == 0x0A000001
    with pytest.raises(InputError, match="PhotronCamera.ip"):
        ip_to_pdc("camera.local")


# -------------------------------------------------------------------- parameter mapping

RATES = [50, 60, 125, 250, 500, 1000, 2000, 5000, 10000, 20000]


def test_record_rate_is_the_nearest_offered():
    assert choose_record_rate(2000, RATES) == 2000
    assert choose_record_rate(1995.0, RATES) == 2000  # within 1 %
    assert choose_record_rate(59.94, list(reversed(RATES))) == 60
    with pytest.raises(InputError, match="TriggerSettings.fps: 3000 fps is not a record rate.*2000 fps and 5000 fps"):
        choose_record_rate(3000, RATES)
    with pytest.raises(InputError, match="range 50 to 20000 fps.*nearest are 20000 fps$"):
        choose_record_rate(100000, RATES)
    with pytest.raises(InputError, match="PDC_GetRecordRateList"):
        choose_record_rate(1000, [])


SHUTTERS = [1000, 2000, 4000, 8000, 10000, 20000, 50000, 100000]  # as 1/s, what the camera lists


def test_shutter_is_the_longest_exposure_within_the_request():
    assert choose_shutter(1e-4, SHUTTERS, 2000) == 10000
    assert choose_shutter(1.5e-4, SHUTTERS, 2000) == 8000       # 1/8000 s = 125 us, never the longer 1/4000
    assert choose_shutter(1 / 2000, SHUTTERS, 2000) == 2000     # a whole frame period
    assert choose_shutter(1 / 1000, SHUTTERS, 1000) == 1000
    with pytest.raises(InputError,
                       match="TriggerSettings.exposure_s: 0.0006 s is longer than the frame period 1/2000 s"):
        choose_shutter(6e-4, SHUTTERS, 2000)
    with pytest.raises(InputError, match="shorter than the shortest shutter of this camera, 1/100000 s"):
        choose_shutter(5e-6, SHUTTERS, 2000)


@pytest.mark.parametrize("pretrigger,pre,after", [("start", 0, 100), ("center", 50, 50), ("end", 99, 1), (30, 30, 70)])
def test_short_recordings_use_manual_with_after_frames(pretrigger, pre, after):
    plan = plan_trigger(TriggerSettings(n_frames=100, pretrigger=pretrigger), max_frames=21_000)
    assert (plan.mode_code, plan.mode_name, plan.after_frames, plan.endless) == \
        (PDC.TRIGGER_MANUAL, "manual", after, True)
    assert (plan.pretrigger_frames, plan.post_frames, plan.n_frames) == (pre, 100 - pre, 100)


@pytest.mark.parametrize("pretrigger,mode,endless", [("start", 0x00000000, False), ("center", 0x01000000, True),
                                                     ("end", 0x02000000, True)])
def test_recordings_filling_the_memory_use_the_cameras_modes(pretrigger, mode, endless):
    plan = plan_trigger(TriggerSettings(n_frames=1000, pretrigger=pretrigger), max_frames=1000)
    assert (plan.mode_code, plan.after_frames, plan.endless) == (mode, 0, endless)


def test_plan_refuses_more_frames_than_the_memory_holds():
    assert plan_trigger(TriggerSettings(n_frames=1000, pretrigger=300), 1000).mode_code == PDC.TRIGGER_MANUAL
    with pytest.raises(InputError, match="TriggerSettings.n_frames: the camera holds at most 1000 frames.*1001"):
        plan_trigger(TriggerSettings(n_frames=1001), 1000)


def test_trigger_mode_encoding_matches_a_real_cameras_file(shared_data):
    # A real SA-Z wrote its PDC trigger mode into the cihx; it follows the header's (mode << 24) encoding.
    text = (shared_data / "pymraw-samples" / "ball_12bit.cihx").read_bytes().decode("utf-8", "ignore")
    pdc_mode = int(re.search(r"<pdcMode>(\d+)</pdcMode>", text).group(1))
    assert pdc_mode == 0x07 << 24  # PDC_TRIGGER_RANDOM_MANUAL in PDCVALUE.h
    modes = [PDC.TRIGGER_START, PDC.TRIGGER_CENTER, PDC.TRIGGER_END, PDC.TRIGGER_MANUAL]
    assert modes == [m << 24 for m in (0, 1, 2, 4)]


# -------------------------------------------------------------------- the recording window

def test_window_cuts_the_memory_to_what_was_asked_for():
    w = select_window(start=-500, end=499, trigger=0, pretrigger=50, post_frames=50)
    assert (w.first_frame, w.last_frame, w.n_frames, w.first_counter, w.pretrigger_available) == (-50, 49, 100, -50, 50)
    # Frame numbers need not count from the trigger.
    w = select_window(start=100, end=1099, trigger=600, pretrigger=10, post_frames=5)
    assert (w.first_frame, w.last_frame, w.first_counter, w.n_frames) == (590, 604, -10, 15)


def test_window_is_short_never_padded():
    armed_late = select_window(start=-7, end=92, trigger=0, pretrigger=50, post_frames=50)
    assert (armed_late.pretrigger_available, armed_late.first_counter, armed_late.n_frames) == (7, -7, 57)
    stopped_early = select_window(start=-50, end=20, trigger=0, pretrigger=50, post_frames=50)
    assert (stopped_early.last_frame, stopped_early.n_frames) == (20, 71)
    assert RecordingWindow(trigger_frame=0, first_frame=0, last_frame=-1).n_frames == 0
    with pytest.raises(InputError,
                       match="PDC_GetMemFrameInfo: trigger frame 200 lies outside the recorded frames 0..99"):
        select_window(start=0, end=99, trigger=200, pretrigger=0, post_frames=10)


# -------------------------------------------------------------------- unpacking

def _pack_12bit_by_loop(values):
    """The .mraw packing written out pixel pair by pixel pair, independently of unpack_12bit."""
    out = bytearray()
    flat = [int(v) for v in np.asarray(values).reshape(-1)]
    for a, b in zip(flat[0::2], flat[1::2]):
        out += bytes([a >> 4, ((a & 0x0F) << 4) | (b >> 8), b & 0xFF])
    return bytes(out)


def test_packed_12bit_unpacks_to_the_values_packed(tmp_path):
    rng = np.random.default_rng(7)
    image = rng.integers(0, 4096, size=(6, 10), dtype=np.uint16)
    image[0, :4] = [0, 4095, 0x0ABC, 0x0123]  # extremes and nibble patterns
    raw = _pack_12bit_by_loop(image)
    assert len(raw) == frame_bytes(10, 6, 12) == 90
    out = unpack_frame(raw, width=10, height=6, bits=12)
    assert out.dtype == np.uint16 and out.shape == (6, 10)
    np.testing.assert_array_equal(out, image)
    np.testing.assert_array_equal(unpack_12bit(np.frombuffer(raw, np.uint8)), image.reshape(-1))
    # pyMRAW reads the loop's bytes the same way: the loop packs as .mraw files are packed.
    (tmp_path / "x.mraw").write_bytes(raw)
    ref = pyMRAW.load_images(str(tmp_path / "x.mraw"), 6, 10, 1, bit=12, roll_axis=False)
    np.testing.assert_array_equal(ref[0], image)


def test_8_and_16_bit_frames():
    img8 = np.arange(12, dtype=np.uint8).reshape(3, 4)
    out8 = unpack_frame(img8.tobytes(), 4, 3, 8)
    np.testing.assert_array_equal(out8, img8)
    assert out8.dtype == np.uint8
    img16 = (np.arange(12, dtype=np.uint16) * 341).reshape(3, 4)
    out16 = unpack_frame(memoryview(img16.tobytes()), 4, 3, 16)
    np.testing.assert_array_equal(out16, img16)
    assert out16.dtype == np.uint16
    buffer = (ctypes.c_ubyte * 24)(*img16.tobytes())  # what PDC_GetMemImageData fills
    out = unpack_frame(memoryview(buffer), 4, 3, 16)
    buffer[0] = 99  # the frame is a copy, not a view of the reused buffer
    np.testing.assert_array_equal(out, img16)


def test_unpacking_refuses_wrong_sizes():
    with pytest.raises(InputError, match="PDC_GetMemImageData: 11 bytes for a 4x3 frame of 8 bits; expected 12"):
        unpack_frame(bytes(11), 4, 3, 8)
    with pytest.raises(InputError, match="packed 12-bit frames of 3x3 do not fill whole bytes"):
        frame_bytes(3, 3, 12)
    with pytest.raises(InputError, match="expected 8, 12 \\(packed\\) or 16, got 10"):
        frame_bytes(4, 4, 10)


def _mraw_frames(shared_data, stem, n_bytes_per_frame, frames):
    raw = np.fromfile(shared_data / "pymraw-samples" / f"{stem}.mraw", dtype=np.uint8)
    return [raw[i * n_bytes_per_frame:(i + 1) * n_bytes_per_frame] for i in frames]


def test_unpacking_matches_pymraw_on_real_recordings(shared_data):
    # ball_12bit: packed 12-bit, 384x384, 15 frames (a real SA-Z recording).
    ref, cih = pyMRAW.load_video(str(shared_data / "pymraw-samples" / "ball_12bit.cihx"))
    w, h = cih["Image Width"], cih["Image Height"]
    for i, raw in zip((0, 7, 14), _mraw_frames(shared_data, "ball_12bit", frame_bytes(w, h, 12), (0, 7, 14))):
        np.testing.assert_array_equal(unpack_frame(raw, w, h, 12), ref[i])
    assert int(ref.max()) == 4095
    # beam: 12-bit data in 16-bit words, low-aligned, 1024x80, 4 frames.
    ref, cih = pyMRAW.load_video(str(shared_data / "pymraw-samples" / "beam.cihx"))
    w, h = cih["Image Width"], cih["Image Height"]
    for i, raw in enumerate(_mraw_frames(shared_data, "beam", frame_bytes(w, h, 16), range(4))):
        np.testing.assert_array_equal(unpack_frame(raw, w, h, 16), ref[i])


# -------------------------------------------------------------------- names

def test_status_and_error_names():
    assert status_name(PDC.STATUS_ENDLESS).startswith("recording endlessly")
    assert status_name(0x02) == "ready to record" and status_name(0x03) == "unknown status 0x03"
    assert error_message(22) == "frame not captured (dropped)" and error_message(9999) == "unknown error"
    err = PdcError("photron:192.168.0.10", "PDC_SetRecordRate", 5)
    assert isinstance(err, InputError) and err.code == 5
    assert str(err) == "photron:192.168.0.10: PDC_SetRecordRate failed with error 5 (illegal parameter)"


# -------------------------------------------------------------------- on a camera (pytest --hardware)

@pytest.fixture
def camera():
    ip = os.environ.get("ODSPLAT_PHOTRON_IP")
    if not ip:
        pytest.skip("set ODSPLAT_PHOTRON_IP to the camera's address (and ODSPLAT_PDCLIB to PDCLIB's path)")
    with PhotronCamera(ip) as cam:
        yield cam


@pytest.mark.hardware
def test_photron_records_around_a_software_trigger(camera):
    info = camera.describe()
    camera.configure(TriggerSettings(n_frames=100, mode="external", pretrigger="center"))
    camera.arm()
    time.sleep(max(0.5, 200 / info.fps))  # long enough to fill the 50 pretrigger frames
    camera.software_trigger()
    status = camera.wait(30.0)
    assert (status.n_frames, status.first_counter, status.pretrigger_available) == (100, -50, 50)
    frames = list(camera.frames())
    assert [f.counter for f in frames] == list(range(-50, 50)) and camera.dropped == ()
    assert frames[0].image.shape == camera.frame_shape and frames[0].image.dtype == camera.dtype
    assert frames[-1].time_s == pytest.approx(49 / info.fps)
    assert int(max(f.image.max() for f in frames)) < 1 << info.bit_depth  # low-aligned deep pixels


@pytest.mark.hardware
def test_photron_internal_trigger_and_timeout(camera):
    camera.configure(TriggerSettings(n_frames=20, mode="internal"))
    camera.arm()
    status = camera.wait(30.0)
    assert (status.n_frames, status.first_counter) == (20, 0)
    assert [f.counter for f in camera.frames()] == list(range(20))
    camera.configure(TriggerSettings(n_frames=20, mode="external"))
    camera.arm()
    with pytest.raises(CameraTimeout, match="waiting for the trigger"):
        camera.wait(0.5)
    camera.stop()
