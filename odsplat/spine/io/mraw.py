"""Photron's packed 12-bit pixels, unpacked in one place: for .mraw files (`odsplat.spine.io.video`) and for the
frames a camera sends (`odsplat.acquisition.photron`).
The unpacking is pyMRAW's numba kernel, run on each chunk read."""
from __future__ import annotations

import numpy as np
import pyMRAW

from odsplat.spine.errors import InputError


def unpack_12bit(raw: np.ndarray | bytes | bytearray | memoryview) -> np.ndarray:
    """Packed 12-bit, as in Photron's .mraw: 3 bytes hold 2 pixels, big-endian (AAAAAAAA AAAABBBB BBBBBBBB).
    Returns a new flat uint16 array of values 0..4095, one per pixel."""
    if isinstance(raw, (bytes, bytearray, memoryview)):
        data = np.frombuffer(raw, dtype=np.uint8)
    else:
        data = np.ascontiguousarray(raw, dtype=np.uint8).reshape(-1)
    if data.size % 3:
        raise InputError("packed 12-bit data", f"{data.size} bytes is not a whole number of 3-byte pixel pairs")
    # The kernel is compiled for C-contiguous uint8; a memmap's rows are, and measured 2.6 times numpy's
    # shifts and masks on a 88 MB file (bench/mraw.py).
    return pyMRAW.nb_read_uint12(data)
