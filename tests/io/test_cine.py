"""open_video on a real Phantom .cine (pyidi's sample), checked against pyidi's reader (cine-handler) and, for the
undecoded 10-bit codes, against pims; damaged copies are refused naming the file and the field."""
from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from cine_reader import Cine

from odsplat.spine.errors import InputError
from odsplat.spine.io.video import open_video

SAMPLE = "pyidi-samples/data_small_cine.cine"
FRAMES = (0, 1, 117, 233, 234)


@pytest.fixture(scope="module")
def cine_path(shared_data) -> Path:
    return shared_data / SAMPLE


@pytest.fixture(scope="module")
def frames(cine_path) -> np.ndarray:
    return np.concatenate(list(open_video(cine_path).iter_chunks(50)))


def test_cine_header_as_the_sample_says(cine_path):
    source = open_video(cine_path)
    # 235 frames of 256x32 at 100 fps (data/README.md); FirstImageNo 0: the first frame is the trigger frame.
    assert (source.n_frames, source.frame_shape, source.n_colors, source.fps) == (235, (32, 256), 1, 100.0)
    assert (source.trigger_frame, source.start_frame, source.frame_step) == (0, 0, 1)
    # Packed 10-bit codes, linearised to 12 bits.
    assert (source.dtype, source.bit_depth) == (np.uint16, 12)
    assert source.camera_model == "Phantom, serial 34497"
    assert source.header["RealBPP"] == 10 and source.header["ShutterNs"] == 70_000


def test_cine_frames_equal_pyidis_reader(cine_path, frames):
    assert frames.shape == (235, 32, 256) and frames.dtype == np.uint16
    assert 0 < frames.min() and frames.max() <= 4095
    reference = Cine(cine_path, keep_annotations=False)
    for i in FRAMES:
        reference.load_frame(i)
        np.testing.assert_array_equal(frames[i], reference.frame)
    source = open_video(cine_path)
    np.testing.assert_array_equal(source.read(117, 120), frames[117:120])


def test_cine_frames_are_pims_codes_through_one_monotonic_table(cine_path, frames):
    """pims unpacks the 10-bit codes on its own and does not linearise them: each code must map to one value of
    ours, never falling as the code rises (Vision Research's LinLUT), the sample's first pixel 624 -> 1481."""
    pims = pytest.importorskip("pims")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reader = pims.Cine(str(cine_path))
        codes = np.stack([np.asarray(reader[i]) for i in FRAMES])
    assert codes.max() <= 1023 and codes[0, 0, 0] == 624 and frames[0, 0, 0] == 1481
    ours = frames[list(FRAMES)]
    table = np.full(1024, -1)
    table[codes.ravel()] = ours.ravel()
    np.testing.assert_array_equal(table[codes], ours)  # one value per code
    seen = table[table >= 0]
    # Non-decreasing: the LinLUT maps a few neighbouring dark codes to one value (codes 13 and 14 to 17).
    assert len(seen) > 500 and np.all(np.diff(seen) >= 0) and seen[-1] - seen[0] > 4000


def _damaged(cine_path: Path, tmp_path: Path, *, keep: int | None = None,
             patch: dict[int, bytes] | None = None) -> Path:
    data = bytearray(cine_path.read_bytes())
    for at, value in (patch or {}).items():
        data[at:at + len(value)] = value
    out = tmp_path / "take.cine"
    out.write_bytes(bytes(data[:keep]))
    return out


def test_truncated_cine_is_refused_at_open(cine_path, tmp_path):
    size = cine_path.stat().st_size
    with pytest.raises(InputError, match=r"truncated: holds 2417424 bytes, 234 whole frames of the 235") as err:
        open_video(_damaged(cine_path, tmp_path, keep=size - 5000))
    assert err.value.source == str(tmp_path / "take.cine")
    with pytest.raises(InputError, match="less than the 44-byte file header"):
        open_video(_damaged(cine_path, tmp_path, keep=30))
    with pytest.raises(InputError, match=r"OffImageOffsets 12264 \+ ImageCount 235"):
        open_video(_damaged(cine_path, tmp_path, keep=12300))


@pytest.mark.parametrize("at, value, message", [
    (0, b"XX", "Type is b'XX', not b'CI'"),
    (6, struct.pack("<H", 7), "Version is 7"),
    (4, struct.pack("<H", 1), "Compression is 1"),
    (20, struct.pack("<I", 0), "ImageCount is 0"),
    (20, struct.pack("<I", 10**8), "OffImageOffsets 12264 \\+ ImageCount 100000000"),
    (44 + 16, struct.pack("<I", 7), "biCompression is 7"),
    (44 + 20, struct.pack("<I", 999), "biSizeImage is 999 bytes"),
])
def test_garbled_cine_header_names_the_field(cine_path, tmp_path, at, value, message):
    with pytest.raises(InputError, match=message):
        open_video(_damaged(cine_path, tmp_path, patch={at: value}))
