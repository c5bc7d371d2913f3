"""Aligned take files, `derived/sync/NAME.h5`: a take's frames resampled onto the capture's common
impact-locked time grid. Written band by band (rows), read frame by frame; never whole in memory.

Layout (HDF5): dataset `frames` (n_grid, H, W[, C]) uint16 holding value * `value_scale`, where value is
in the raw take's digital numbers (DN) and `value_scale` is 4 (1 for 15- and 16-bit cameras), so a
quarter DN of the detail a fractional delay creates survives, far below the sensor's noise; dataset `times_s` (n_grid,), each frame's mid-exposure time after
the impact onset. Attributes name the take, its offset, method and impulse scale.
"""
from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from odsplat.errors import InputError, SchemaError
from odsplat.store import frame_compression, fsync_path

KIND = "odsplat-aligned-take"


class AlignedWriter:
    """Creates `path` as a temporary file; `close()` fsyncs and renames it into place."""

    def __init__(self, path: Path, *, n_frames: int, frame_shape: tuple[int, ...], band_rows: int, bit_depth: int,
                 times_s: np.ndarray, attrs: dict[str, Any]):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        self.scale = float(2 ** max(0, min(2, 16 - bit_depth)))
        self._file = h5py.File(self._tmp, "w")
        f = self._file
        f.attrs.update(kind=KIND, format_version=1, bit_depth=bit_depth, value_scale=self.scale,
                       **{k: v for k, v in attrs.items() if v is not None})
        chunks = (1, min(band_rows, frame_shape[0]), *frame_shape[1:])
        self._frames = f.create_dataset("frames", shape=(n_frames, *frame_shape), dtype=np.uint16, chunks=chunks,
                                        **frame_compression())
        f.create_dataset("times_s", data=np.asarray(times_s, float))

    def write_band(self, rows: slice, values_dn: np.ndarray) -> None:
        """values_dn: (n_frames, rows, W[, C]) in the raw take's DN."""
        v = np.clip(np.rint(values_dn * self.scale), 0, 65535).astype(np.uint16)
        self._frames[:, rows] = v

    def close(self) -> Path:
        self._file.close()
        with open(self._tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(self._tmp, self.path)
        fsync_path(self.path.parent)
        return self.path

    def abort(self) -> None:
        try:
            self._file.close()
        finally:
            self._tmp.unlink(missing_ok=True)


class AlignedTake:
    """Reads an aligned take: frames as float32 in the raw take's DN, on the common grid."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        try:
            self._file = h5py.File(self.path, "r")
        except FileNotFoundError:
            raise InputError(self.path, "no such aligned take (run `odsplat sync` first)") from None
        except OSError as exc:
            raise InputError(self.path, f"cannot be opened as HDF5 ({exc})") from None
        if self._file.attrs.get("kind") != KIND:
            self._file.close()
            raise SchemaError(self.path, f"not an aligned take file (kind {KIND!r} expected)")
        self.scale = float(self._file.attrs["value_scale"])

    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self._file.attrs)

    @property
    def n_frames(self) -> int:
        return int(self._file["frames"].shape[0])

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self._file["frames"].shape[1:])

    @property
    def times_s(self) -> np.ndarray:
        return self._file["times_s"][:]

    def read_frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        return self._file["frames"][start:stop].astype(np.float32) / self.scale

    def iter_frames(self, chunk_frames: int = 16) -> Iterator[np.ndarray]:
        for k in range(0, self.n_frames, chunk_frames):
            yield self.read_frames(k, k + chunk_frames)

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> AlignedTake:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["AlignedTake", "AlignedWriter"]
