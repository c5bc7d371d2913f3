"""Aligned take files, `derived/sync/NAME.h5`: a take's frames resampled onto the capture's common
impact-locked time grid, in the spine's derived frame-file layout (`odsplat.spine.framefile`). Written band by
band (rows), read frame by frame; never whole in memory. `times_s` holds each frame's mid-exposure time
after the impact onset; attributes name the take, its offset, method and impulse scale.
"""
from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.framefile import ALIGNED_KIND, FrameFile, atomic_h5, create_frames, to_stored


@contextlib.contextmanager
def write_aligned(path: Path, *, n_frames: int, frame_shape: tuple[int, ...], band_rows: int, bit_depth: int,
                  times_s: np.ndarray, attrs: dict[str, Any], capture_id: str | None = None
                  ) -> Iterator[Callable[[slice, np.ndarray], None]]:
    """Yields `write_band(rows, values_dn)` for (n_frames, rows, W[, C]) bands in the raw take's DN; the file
    appears at `path` only when the block ends without an error. `capture_id`: the capture's, recorded in it."""
    with atomic_h5(path) as f:
        ds, scale = create_frames(f, ALIGNED_KIND, frame_shape=frame_shape, bit_depth=bit_depth, times_s=times_s,
                                  n_frames=n_frames, chunk_rows=band_rows, attrs=attrs, capture_id=capture_id)

        def write_band(rows: slice, values_dn: np.ndarray) -> None:
            ds[:, rows] = to_stored(values_dn, scale)

        yield write_band


class AlignedTake(FrameFile):
    """Reads an aligned take: frames as float32 in the raw take's DN, on the common grid."""

    KIND = ALIGNED_KIND
    WHAT = "aligned take file"
    MISSING = "no such aligned take (run `odsplat sync` first)"


__all__ = ["AlignedTake", "write_aligned"]
