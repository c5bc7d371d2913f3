"""open_video on real Photron recordings (checked against pyMRAW) and on sequences, arrays and videos written here."""
from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from odsplat.spine.errors import InputError
from odsplat.spine.io.video import open_video

pyMRAW = pytest.importorskip("pyMRAW")

# (file, frames, (H, W), fps in this file, bit depth, dtype, start frame, trigger index)
PHOTRON_SAMPLES = [
    ("pymraw-samples/ball_12bit.cihx", 15, (384, 384), 30000.0, 12, np.uint16, 52, None),
    # beam.cihx says skipFrame 2500 for 4 frames out of 400 recorded: contradictory, so step 1.
    ("pymraw-samples/beam.cihx", 4, (80, 1024), 50000.0, 12, np.uint16, 0, 0),
    # Save Step 100 of a 15 kHz recording: the file's frames lie 1/150 s apart.
    ("pyidi-samples/data_showcase.cih", 75, (40, 640), 150.0, 8, np.uint8, 0, 0),
    ("ladisk-imaging-tutorial/focus.cih", 1, (40, 640), 50.0, 8, np.uint8, 0, 0),
]


def _pymraw_frames(cih: Path) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pyMRAW warns about anything but 12-bit
        images, _ = pyMRAW.load_video(str(cih))
    return np.array(images)


def _copy_photron(shared_data: Path, rel: str, dest: Path, mraw_bytes: int | None = None) -> Path:
    """The sample's header and (a prefix of) its .mraw, in dest."""
    src = shared_data / rel
    cih = dest / src.name
    shutil.copyfile(src, cih)
    data = src.with_suffix(".mraw").read_bytes()
    cih.with_suffix(".mraw").write_bytes(data if mraw_bytes is None else data[:mraw_bytes])
    return cih


@pytest.mark.parametrize("rel, n, hw, fps, bits, dtype, start, trigger", PHOTRON_SAMPLES)
def test_photron_sample_matches_pymraw(shared_data, rel, n, hw, fps, bits, dtype, start, trigger):
    cih = shared_data / rel
    source = open_video(cih)
    assert (source.n_frames, source.frame_shape, source.n_colors) == (n, hw, 1)
    assert source.fps == pytest.approx(fps)
    assert (source.bit_depth, source.dtype) == (bits, np.dtype(dtype))
    assert (source.start_frame, source.trigger_frame) == (start, trigger)
    assert source.camera_model.startswith("FASTCAM")
    frames = np.concatenate(list(source.iter_chunks(chunk_frames=4)))
    assert frames.dtype == dtype and frames.shape == (n, *hw)
    assert frames.max() <= 2**bits - 1
    # The samples are Lower-side or 8-bit, so pyMRAW's unshifted values are the reference.
    np.testing.assert_array_equal(frames, _pymraw_frames(cih))


def test_photron_read_middle_of_packed_12bit_and_open_by_mraw(shared_data):
    cih = shared_data / "pymraw-samples/ball_12bit.cihx"
    reference = _pymraw_frames(cih)
    source = open_video(cih.with_suffix(".mraw"))
    assert source.path == cih
    np.testing.assert_array_equal(source.read(5, 9), reference[5:9])
    assert source.read(3, 3).shape == (0, 384, 384)
    with pytest.raises(IndexError):
        source.read(10, 16)


def test_photron_header_is_json_ready(shared_data):
    import json

    for rel, *_ in PHOTRON_SAMPLES:
        header = open_video(shared_data / rel).header
        assert json.loads(json.dumps(header)) == header


def _write_cih(path: Path, **fields: object) -> None:
    lines = {"Record Rate(fps)": 1000, "Total Frame": 3, "Start Frame": -1, "Image Width": 5, "Image Height": 4,
             "Color Type": "Mono", "Color Bit": 16, "File Format": "MRaw", "EffectiveBit Depth": 12,
             "EffectiveBit Side": "Higher", "Camera Type": "test camera"} | fields
    path.write_text("#Camera Information Header\n" + "".join(f"{k} : {v}\n" for k, v in lines.items()) + "\nEND\n")


def test_photron_16bit_higher_side_is_shifted_to_12bit(tmp_path):
    values = np.random.default_rng(0).integers(0, 4096, size=(3, 4, 5), dtype=np.uint16)
    _write_cih(tmp_path / "hi.cih")
    (values << 4).astype("<u2").tofile(tmp_path / "hi.mraw")
    source = open_video(tmp_path / "hi.cih")
    assert (source.bit_depth, source.dtype, source.camera_model) == (12, np.uint16, "test camera")
    # Start Frame -1: camera frame 0, the trigger, is the file's second frame.
    assert (source.start_frame, source.trigger_frame) == (-1, 1)
    np.testing.assert_array_equal(source.read(0, 3), values)
    np.testing.assert_array_equal(source.read(0, 3), _pymraw_frames(tmp_path / "hi.cih") >> 4)


def test_photron_color_8bit_round_trip(tmp_path):
    values = np.random.default_rng(1).integers(0, 256, size=(2, 4, 6, 3), dtype=np.uint8)
    _write_cih(tmp_path / "rgb.cih", **{"Color Type": "Color", "Color Bit": 8, "Total Frame": 2, "Image Width": 6})
    values.tofile(tmp_path / "rgb.mraw")
    source = open_video(tmp_path / "rgb.cih")
    assert (source.frame_shape, source.bit_depth) == ((4, 6, 3), 8)
    np.testing.assert_array_equal(source.read(0, 2), values)


def test_photron_truncated_mraw_names_it(shared_data, tmp_path):
    cih = _copy_photron(shared_data, "pymraw-samples/ball_12bit.cihx", tmp_path, mraw_bytes=1_000_000)
    with pytest.raises(InputError, match="truncated") as err:
        open_video(cih)
    assert err.value.source == str(cih.with_suffix(".mraw"))
    assert ("truncated: holds 1000000 bytes (4.521 frames), ball_12bit.cihx declares 15 frames of 384x384 at 12 bit "
            "= 3317760 bytes") in str(err.value)


@pytest.mark.parametrize("field, value", [("Total Frame", "70"), ("Total Frame", "80"),
                                          ("Image Width", "600"), ("Image Width", "700")])
def test_photron_edited_header_names_both_files(shared_data, tmp_path, field, value):
    cih = _copy_photron(shared_data, "pyidi-samples/data_showcase.cih", tmp_path)
    text = cih.read_text()
    old = next(line for line in text.splitlines() if line.startswith(field + " :"))
    cih.write_text(text.replace(old, f"{field} : {value}"))
    with pytest.raises(InputError) as err:
        open_video(cih)
    assert "data_showcase.mraw" in str(err.value) and "data_showcase.cih" in str(err.value)
    assert "1920000 bytes" in str(err.value)


def test_photron_missing_mraw_and_bad_bit_depth(tmp_path):
    _write_cih(tmp_path / "alone.cih")
    with pytest.raises(InputError, match="alone.mraw"):
        open_video(tmp_path / "alone.cih")
    _write_cih(tmp_path / "ten.cih", **{"Color Bit": 10})
    (tmp_path / "ten.mraw").write_bytes(bytes(75))
    with pytest.raises(InputError, match="Color Bit 10 is not supported"):
        open_video(tmp_path / "ten.cih")


def test_photron_fps_must_agree(shared_data):
    cih = shared_data / "pymraw-samples/ball_12bit.cihx"
    assert open_video(cih, fps=30000).fps == 30000
    with pytest.raises(InputError, match="30000 fps"):
        open_video(cih, fps=25000)


# ---------------------------------------------------------------- image sequences and arrays

def _write_sequence(folder: Path, frames: np.ndarray, suffix: str = ".png") -> None:
    folder.mkdir()
    for i, frame in enumerate(frames):
        bgr = frame[..., ::-1] if frame.ndim == 3 else frame
        assert cv2.imwrite(str(folder / f"frame_{i + 1}{suffix}"), bgr)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("colors", [1, 3])
def test_png_sequence_round_trip(tmp_path, dtype, colors):
    shape = (12, 6, 8) if colors == 1 else (12, 6, 8, 3)
    frames = np.random.default_rng(2).integers(0, np.iinfo(dtype).max, size=shape, endpoint=True, dtype=dtype)
    _write_sequence(tmp_path / "seq", frames)  # frame_1 .. frame_12: frame_10 must come after frame_9
    source = open_video(tmp_path / "seq", fps=5000)
    assert (source.n_frames, source.frame_shape, source.n_colors) == (12, shape[1:], colors)
    assert (source.dtype, source.bit_depth, source.fps) == (np.dtype(dtype), 8 * np.dtype(dtype).itemsize, 5000)
    assert (source.trigger_frame, source.start_frame) == (None, None)
    np.testing.assert_array_equal(np.concatenate(list(source.iter_chunks(5))), frames)
    np.testing.assert_array_equal(source.read(8, 11), frames[8:11])


def test_tiff_sequence_of_12bit_data_reports_16(tmp_path):
    frames = np.random.default_rng(3).integers(0, 4096, size=(3, 5, 7), dtype=np.uint16)
    _write_sequence(tmp_path / "tif", frames, ".tif")
    source = open_video(tmp_path / "tif")
    assert (source.bit_depth, source.fps) == (16, None)
    np.testing.assert_array_equal(source.read(0, 3), frames)


def test_sequence_with_a_different_frame_names_it(tmp_path):
    frames = np.zeros((4, 6, 8), dtype=np.uint8)
    _write_sequence(tmp_path / "seq", frames)
    cv2.imwrite(str(tmp_path / "seq" / "frame_3.png"), np.zeros((6, 9), dtype=np.uint8))
    source = open_video(tmp_path / "seq")
    with pytest.raises(InputError, match="is 9x6 uint8, but the sequence's first image frame_1.png is 8x6") as err:
        source.read(0, 4)
    assert err.value.source.endswith("frame_3.png")
    cv2.imwrite(str(tmp_path / "seq" / "frame_3.png"), np.zeros((6, 8), dtype=np.uint16))
    with pytest.raises(InputError, match="uint16"):
        list(source.iter_chunks())


def test_empty_folder_and_unknown_kind(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no .png"):
        open_video(tmp_path / "empty")
    (tmp_path / "take.raw").write_bytes(b"\0")
    with pytest.raises(InputError, match=r"take.raw: is not a supported recording; expected .*\.cine.*\.npy"):
        open_video(tmp_path / "take.raw")
    with pytest.raises(InputError, match="does not exist"):
        open_video(tmp_path / "nowhere.mp4")


@pytest.mark.parametrize("shape, dtype", [((5, 4, 6), np.uint8), ((5, 4, 6, 3), np.uint16)])
def test_npy_round_trip(tmp_path, shape, dtype):
    frames = np.random.default_rng(4).integers(0, 4000, size=shape).astype(dtype)
    np.save(tmp_path / "take.npy", frames)
    source = open_video(tmp_path / "take.npy", fps=100.0)
    assert (source.frame_shape, source.dtype, source.fps) == (shape[1:], np.dtype(dtype), 100.0)
    assert isinstance(source.array, np.memmap)
    np.testing.assert_array_equal(np.concatenate(list(source.iter_chunks(2))), frames)


def test_npy_of_other_dtype_or_shape_is_refused(tmp_path):
    np.save(tmp_path / "float.npy", np.zeros((2, 3, 4), dtype=np.float32))
    with pytest.raises(InputError, match="float.npy: has dtype float32; accepted: uint8 or uint16"):
        open_video(tmp_path / "float.npy")
    np.save(tmp_path / "flat.npy", np.zeros((2, 3), dtype=np.uint8))
    with pytest.raises(InputError, match=r"has shape \(2, 3\)"):
        open_video(tmp_path / "flat.npy")


# ---------------------------------------------------------------- video files

def test_video_file_tacoma(shared_data):
    path = shared_data / "pyidi-samples/tacoma_bridge.mp4"
    capture = cv2.VideoCapture(str(path))
    decoded = []
    while (frame := capture.read()[1]) is not None:
        decoded.append(frame)
    source = open_video(path)
    assert (source.n_frames, source.frame_shape) == (len(decoded), decoded[0].shape)
    assert (source.fps, source.dtype, source.bit_depth) == (30.0, np.uint8, 8)
    np.testing.assert_array_equal(source.read(100, 103), np.stack(decoded[100:103])[..., ::-1])
    np.testing.assert_array_equal(source.read(0, 2), np.stack(decoded[:2])[..., ::-1])  # rewinds
    with pytest.raises(InputError, match="30 fps"):
        open_video(path, fps=60)


def test_video_file_written_here(tmp_path):
    path = tmp_path / "take.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), 250.0, (64, 48))
    for i in range(10):
        frame = np.zeros((48, 64, 3), dtype=np.uint8)
        frame[..., 2] = 200  # red in BGR
        frame[:, : 6 * i + 4] = 0
        writer.write(frame)
    writer.release()
    source = open_video(path)
    assert (source.n_frames, source.frame_shape, source.fps, source.n_colors) == (10, (48, 64, 3), 250.0, 3)
    frames = np.concatenate(list(source.iter_chunks(4)))
    red = frames[..., 0].astype(int)
    assert red[:, :, -1].mean() > 190 and frames[..., 2].mean() < 10  # RGB order, not BGR
    dark = (red < 100).sum(axis=2).mean(axis=1)  # dark columns per frame: 4, 10, 16, ...
    np.testing.assert_allclose(dark, 6 * np.arange(10) + 4, atol=1.5)
    np.testing.assert_array_equal(source.read(5, 7), frames[5:7])
