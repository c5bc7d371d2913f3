"""Derived frame files (`derived/sync/NAME.h5`, `derived/magnified/METHOD/NAME.h5`): frames computed from a
take, written once (temporary file, fsync, rename) and read back in chunks. One layout for every stage.

Layout (HDF5): attributes `kind` (what the file holds: `ALIGNED_KIND` or `MAGNIFIED_KIND`) and `schema_version`
(`SCHEMA`), as every derived file describes itself (odsplat.contract), and `generation`, the id of the stage
run that wrote it, which the stage's index file (sync.json, magnify.json) records too: a reader given the index's
generation refuses a file of another run (`begin_outputs`); dataset `frames` (n, H, W[, C]) uint16 holds
value * `value_scale`, value in the source take's digital numbers (DN), `value_scale` 4 (1 for 15- and
16-bit cameras) so that a quarter DN of the sub-DN detail resampling and filtering create survives, far
below the sensor's noise; dataset `times_s` (n,), each frame's time; `bit_depth` of the source.
"""
from __future__ import annotations

import contextlib
import uuid
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

import h5py
import numpy as np

from .errors import InputError, SchemaError
from .store import atomic_path, frame_compression, fsync_path, remove_stale_temporaries

ALIGNED_KIND = "odsplat.aligned-take"        # sync's frames on the common grid
MAGNIFIED_KIND = "odsplat.magnified-take"    # processing's magnified frames
SCHEMA = 3   # 3: the generation attribute


# ------------------------------------------------------------------ a stage's outputs, committed together

def begin_outputs(index: Path, folder: Path) -> str:
    """Start a run of a stage that writes a folder of frame files and then their index (sync, magnify): the old
    index goes first, durably, so a run killed from here on leaves no index and no reader takes its files as a
    set; temporaries of killed runs are removed. Returns the new run's generation id, for every file it writes."""
    if index.exists():
        index.unlink()
        fsync_path(index.parent)
    remove_stale_temporaries(folder)
    return uuid.uuid4().hex[:16]


OUTPUT_PATTERNS = ("*.h5", "*.mp4")   # a stage's files in its folder: frames, and the videos made from them


def _outputs(folder: Path) -> list[Path]:
    return [p for pattern in OUTPUT_PATTERNS for p in folder.glob(pattern)] if folder.is_dir() else []


def discard_outputs(folder: Path) -> None:
    """After a failed run: remove the folder's frame files and videos, which no index lists any more
    (`begin_outputs` removed the old one), so no reader finds half a set."""
    for path in _outputs(folder):
        path.unlink(missing_ok=True)


def prune_outputs(folder: Path, keep: Iterable[Path]) -> None:
    """After the index is written: remove the frame files and videos in `folder` it does not list (a take no
    longer selected, videos turned off, another run's leftovers)."""
    keep = {Path(p).resolve() for p in keep}
    for path in _outputs(folder):
        if path.resolve() not in keep:
            path.unlink()


def value_scale(bit_depth: int) -> float:
    """How much finer than a DN the stored values are: up to 2 extra bits, within 16."""
    return float(2 ** max(0, min(2, 16 - int(bit_depth))))


def to_stored(values_dn: np.ndarray, scale: float) -> np.ndarray:
    """DN (float) to the stored uint16: rounded, clipped to the 16-bit range."""
    return np.clip(np.rint(values_dn * scale), 0, 65535).astype(np.uint16)


@contextlib.contextmanager
def atomic_h5(path: str | Path) -> Iterator[h5py.File]:
    """An HDF5 file that appears at `path` only once written whole (`store.atomic_path`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        yield f


def create_frames(f: h5py.File, kind: str, *, frame_shape: tuple[int, ...], bit_depth: int, times_s: np.ndarray,
                  n_frames: int | None = None, chunk_rows: int | None = None,
                  attrs: Mapping[str, Any] | None = None) -> tuple[h5py.Dataset, float]:
    """The `frames` dataset (n_frames long, or growable from 0 when None) and `times_s`, with the file's
    attributes; returns the dataset and its value scale. Chunks are one frame, or bands of `chunk_rows`
    rows for writers that go band by band."""
    scale = value_scale(bit_depth)
    f.attrs.update(kind=kind, schema_version=SCHEMA, bit_depth=int(bit_depth), value_scale=scale,
                   **{k: v for k, v in (attrs or {}).items() if v is not None})
    rows = frame_shape[0] if chunk_rows is None else min(chunk_rows, frame_shape[0])
    n = 0 if n_frames is None else n_frames
    ds = f.create_dataset("frames", shape=(n, *frame_shape), maxshape=(n_frames, *frame_shape), dtype=np.uint16,
                          chunks=(1, rows, *frame_shape[1:]), **frame_compression())
    f.create_dataset("times_s", data=np.asarray(times_s, float))
    return ds, scale


class FrameFile:
    """Reads a derived frame file: frames as float32 in the source take's DN. Subclasses name the kind."""

    KIND: ClassVar[str] = ""
    KINDS: ClassVar[tuple[str, ...]] = ()  # when set, any of these kinds is accepted instead of KIND alone
    WHAT: ClassVar[str] = "derived frame file"
    MISSING: ClassVar[str] = "no such file"

    def __init__(self, path: str | Path, generation: str | None = None):
        """`generation`: the index's (sync.json's, magnify.json's); a file of another run is refused."""
        self.path = Path(path)
        try:
            self._file = h5py.File(self.path, "r")
        except FileNotFoundError:
            raise InputError(self.path, self.MISSING) from None
        except OSError as exc:
            raise InputError(self.path, f"cannot be opened as HDF5 ({exc})") from None
        kinds = self.KINDS or (self.KIND,)
        if self._file.attrs.get("kind") not in kinds:
            self._file.close()
            raise SchemaError(self.path, f"not a {self.WHAT} (kind {' or '.join(map(repr, kinds))} expected)")
        version = self._file.attrs.get("schema_version")
        if version != SCHEMA:
            self._file.close()
            raise SchemaError(self.path, f"{self.WHAT} of schema {version}; this odsplat reads {SCHEMA}"
                              + (" (update odsplat)" if isinstance(version, (int, np.integer)) and version > SCHEMA
                                 else " (run its stage again)"))
        self.scale = float(self._file.attrs["value_scale"])
        if generation is not None and self._file.attrs.get("generation") != generation:
            self._file.close()
            raise InputError(self.path, "written by another run of its stage than its index lists (a run was "
                                        "interrupted): run the stage again")

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

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


__all__ = ["FrameFile", "atomic_h5", "begin_outputs", "create_frames", "discard_outputs", "prune_outputs", "to_stored",
           "value_scale"]
