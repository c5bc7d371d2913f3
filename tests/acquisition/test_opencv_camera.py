"""OpenCVCamera on a real video file: triggers, pretrigger ring buffer, counters, early end, timeouts."""
from __future__ import annotations

import logging
import os
import time

import cv2
import numpy as np
import pytest

from odsplat.acquisition.camera import CameraDriver, CameraTimeout, TriggerSettings
from odsplat.acquisition.opencv_camera import OpenCVCamera
from odsplat.spine.errors import InputError, OdsplatError

N_FILE = 120       # frames in the test video
FILE_FPS = 200.0   # its frame rate: 5 ms a frame when played in real time
W, H = 64, 48
PATCH_BGR = (30, 60, 200)  # the colour patch below the code stripes (OpenCV order: blue, green, red)


def _write_video(path, n=N_FILE, fps=FILE_FPS):
    """An MJPG file whose frame i shows i in binary: 8 stripes of 8 px (white = 1, MSB first) over a
    colour patch. Stripes on JPEG's 8x8 blocks survive compression; the index decodes exactly."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (W, H))
    assert writer.isOpened()
    for i in range(n):
        img = np.empty((H, W, 3), np.uint8)
        bits = [(i >> (7 - b)) & 1 for b in range(8)]
        img[:32] = np.repeat([230 if bit else 25 for bit in bits], 8)[None, :, None]
        img[32:] = PATCH_BGR
        writer.write(img)
    writer.release()
    return path


def _index(image):
    """The frame index a frame shows (mono or RGB)."""
    grey = image if image.ndim == 2 else image.mean(axis=2)
    stripes = grey[:32].reshape(32, 8, 8).mean(axis=(0, 2))
    assert np.all(np.abs(stripes - 127.5) > 60), f"stripes do not decode cleanly: {stripes}"
    return int(sum(1 << (7 - b) for b in range(8) if stripes[b] > 127.5))


@pytest.fixture(scope="module")
def video(tmp_path_factory):
    return _write_video(tmp_path_factory.mktemp("video") / "code.avi")


def _camera(video, **kw):
    kw.setdefault("realtime", False)
    return OpenCVCamera(video, **kw)


def _wait_for(predicate, timeout_s=5.0):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached"
        time.sleep(0.001)


def _record(cam, settings, timeout_s=5.0):
    cam.configure(settings)
    cam.arm()
    status = cam.wait(timeout_s)
    return status, list(cam.frames())


def test_describe_shape_and_protocol(video):
    with _camera(video) as cam:
        assert isinstance(cam, CameraDriver)
        info = cam.describe()
        assert info.model.startswith("opencv:")
        assert (info.width_px, info.height_px, info.fps, info.bit_depth, info.n_colors) == (W, H, FILE_FPS, 8, 1)
        assert cam.frame_shape == (H, W) and cam.dtype == np.uint8
        assert cam.name == "opencv:code.avi"


def test_internal_trigger_records_from_the_arm_and_each_arm_replays_the_file(video):
    with _camera(video) as cam:
        for _ in range(2):
            status, frames = _record(cam, TriggerSettings(n_frames=10, mode="internal"))
            assert (status.n_frames, status.first_counter, status.pretrigger_available, status.dropped) == \
                (10, 0, 0, ())
            assert [f.counter for f in frames] == list(range(10))
            assert [_index(f.image) for f in frames] == list(range(10))
            assert [f.time_s for f in frames] == pytest.approx([c / FILE_FPS for c in range(10)])
            assert all(f.image.shape == (H, W) and f.image.dtype == np.uint8 for f in frames)


def test_internal_trigger_has_no_pretrigger_frames(video):
    # As the simulated camera: armed at the trigger, the ring is empty; the frames after it still come.
    with _camera(video) as cam:
        status, frames = _record(cam, TriggerSettings(n_frames=10, mode="internal", pretrigger="center"))
        assert (status.n_frames, status.first_counter, status.pretrigger_available) == (5, 0, 0)
        assert [_index(f.image) for f in frames] == list(range(5))


@pytest.mark.parametrize("pretrigger,pre", [("start", 0), ("center", 10), ("end", 19), (7, 7)])
def test_software_trigger_places_counter_zero_on_the_next_frame(video, pretrigger, pre):
    with _camera(video, realtime=True) as cam:
        cam.configure(TriggerSettings(n_frames=20, mode="external", pretrigger=pretrigger))
        cam.arm()
        _wait_for(lambda: cam.frames_read >= 25)
        cam.software_trigger()
        status = cam.wait(5.0)
        frames = list(cam.frames())
    by_counter = {f.counter: _index(f.image) for f in frames}
    k = by_counter[0]  # file frame that was read first after the trigger call
    assert k >= 25
    assert (status.n_frames, status.first_counter, status.pretrigger_available) == (20, -pre, pre)
    assert [f.counter for f in frames] == list(range(-pre, 20 - pre))
    assert all(index == k + counter for counter, index in by_counter.items())  # contiguous, none lost
    assert [f.time_s for f in frames] == pytest.approx([c / FILE_FPS for c in range(-pre, 20 - pre)])


def test_armed_too_recently_gives_fewer_pretrigger_frames(video):
    with _camera(video, realtime=True) as cam:
        cam.configure(TriggerSettings(n_frames=20, mode="external", pretrigger="end"))
        cam.arm()
        cam.software_trigger()
        status = cam.wait(5.0)
        frames = list(cam.frames())
    k = _index(frames[-1].image)
    assert frames[-1].counter == 0
    assert status.pretrigger_available == k < 19
    assert (status.n_frames, status.first_counter) == (k + 1, -k)
    assert [_index(f.image) for f in frames] == list(range(k + 1))


def test_end_of_file_ends_an_internal_recording_early(video, caplog):
    with _camera(video) as cam:
        status, frames = _record(cam, TriggerSettings(n_frames=200, mode="internal"))
    assert (status.n_frames, status.first_counter) == (N_FILE, 0)
    assert [_index(f.image) for f in frames] == list(range(N_FILE))
    assert "ended after 120 of 200 frames" in caplog.text


def test_end_of_file_after_the_trigger_gives_a_short_recording(video):
    with _camera(video, realtime=True) as cam:
        cam.configure(TriggerSettings(n_frames=50, mode="external", pretrigger=5))
        cam.arm()
        _wait_for(lambda: cam.frames_read >= 100)
        cam.software_trigger()
        status = cam.wait(5.0)
        frames = list(cam.frames())
    k = {f.counter: _index(f.image) for f in frames}[0]
    assert status.n_frames == 5 + (N_FILE - k) < 50  # not padded to 50
    assert _index(frames[-1].image) == N_FILE - 1 and frames[-1].counter == N_FILE - 1 - k


def test_end_of_file_before_the_trigger_is_an_error(video):
    with _camera(video) as cam:
        cam.configure(TriggerSettings(n_frames=10, mode="external"))
        cam.arm()
        with pytest.raises(InputError, match="ended after 120 frames, before any trigger"):
            cam.wait(5.0)
        with pytest.raises(OdsplatError, match="no complete recording"):
            list(cam.frames())


def test_wait_times_out_naming_the_camera(video):
    # fps=50 plays the 120 frames over 2.4 s: the file cannot end during these waits.
    with _camera(video, realtime=True, fps=50.0, name="dry-cam") as cam:
        cam.configure(TriggerSettings(n_frames=10, mode="external"))
        cam.arm()
        t0 = time.monotonic()
        with pytest.raises(CameraTimeout, match=r"^dry-cam: no trigger within 0.2 s"):
            cam.wait(0.2)
        assert 0.2 <= time.monotonic() - t0 < 10 * 0.2  # never before its timeout; 10x above, for a loaded machine
        cam.stop()
        with pytest.raises(OdsplatError, match="arm"):
            list(cam.frames())

        cam.configure(TriggerSettings(n_frames=100, mode="internal"))
        cam.arm()
        with pytest.raises(CameraTimeout, match=r"dry-cam: recording incomplete after 0.1 s: \d+ of 100 frames"):
            cam.wait(0.1)
        assert cam.describe().fps == 50.0


def test_rgb_keeps_colour_and_mono_mixes_it(video):
    with _camera(video, rgb=True) as cam:
        assert cam.frame_shape == (H, W, 3) and cam.describe().n_colors == 3
        _, frames = _record(cam, TriggerSettings(n_frames=3, mode="internal"))
    r, g, b = frames[1].image[40:, :].reshape(-1, 3).mean(axis=0)
    assert (r, g, b) == pytest.approx(PATCH_BGR[::-1], abs=6)
    assert _index(frames[1].image) == 1
    with _camera(video) as cam:
        _, frames = _record(cam, TriggerSettings(n_frames=3, mode="internal"))
    expected_grey = 0.299 * PATCH_BGR[2] + 0.587 * PATCH_BGR[1] + 0.114 * PATCH_BGR[0]
    assert frames[1].image[40:].mean() == pytest.approx(expected_grey, abs=6)


def test_bad_sources_name_what_was_asked_for(tmp_path):
    missing = tmp_path / "nope.avi"
    with pytest.raises(InputError, match=f"{missing}: no such video file"):
        OpenCVCamera(missing)
    text = tmp_path / "notes.avi"
    text.write_text("not a video")
    with pytest.raises(InputError, match=f"{text}: cannot be opened as a video"):
        OpenCVCamera(text)
    with pytest.raises(InputError, match="camera device 99: cannot be opened"):
        OpenCVCamera(99)
    with pytest.raises(InputError, match="OpenCVCamera.source"):
        OpenCVCamera(True)
    with pytest.raises(InputError, match="OpenCVCamera.fps"):
        OpenCVCamera(tmp_path / "x.avi", fps=0)


def test_calls_out_of_order_are_refused(video, caplog):
    with _camera(video, realtime=True, fps=50.0) as cam:
        with pytest.raises(OdsplatError, match="arm\\(\\) before configure"):
            cam.arm()
        with pytest.raises(OdsplatError, match="software_trigger\\(\\) before arm"):
            cam.software_trigger()
        with pytest.raises(OdsplatError, match="wait\\(\\) without an armed recording"):
            cam.wait(0.1)
        with caplog.at_level(logging.WARNING):
            cam.configure(TriggerSettings(n_frames=5, mode="internal", exposure_s=1e-3))
        assert "exposure" in caplog.text
        cam.configure(TriggerSettings(n_frames=100, mode="internal"))
        cam.arm()
        with pytest.raises(OdsplatError, match="internal trigger"):
            cam.software_trigger()
        with pytest.raises(OdsplatError, match="configure\\(\\) while armed"):
            cam.configure(TriggerSettings(n_frames=5))
        cam.stop()


@pytest.mark.hardware
def test_a_uvc_camera_records_around_a_software_trigger():
    index = os.environ.get("ODSPLAT_UVC_INDEX")
    if index is None:
        pytest.skip("set ODSPLAT_UVC_INDEX to a UVC camera's device index")
    with OpenCVCamera(int(index)) as cam:
        cam.configure(TriggerSettings(n_frames=20, mode="external", pretrigger=5))
        cam.arm()
        _wait_for(lambda: cam.frames_read >= 10, timeout_s=10.0)
        cam.software_trigger()
        status = cam.wait(10.0)
        frames = list(cam.frames())
    assert (status.n_frames, status.first_counter, status.pretrigger_available) == (20, -5, 5)
    assert [f.counter for f in frames] == list(range(-5, 15))
    assert all(f.image.shape == cam.frame_shape for f in frames)
