"""Derived frame files (`derived/magnified/METHOD/NAME.h5`): frames computed from a take, written once (temporary
file, fsync, rename) and read back in chunks. Sync's aligned takes (`derived/sync/NAME.h5`) share the folder rules
and the kind's name here, but hold how to compute their frames, not the frames (`odsplat.sync.aligned`).

Layout (HDF5): attributes `kind` (what the file holds: `ALIGNED_KIND` or `MAGNIFIED_KIND`) and `schema_version`
(`SCHEMA`), as every derived file describes itself (odsplat.spine.contract), and `generation`, the id of the stage
run that wrote it, which the stage's index file (sync.json, magnify.json) records too: a reader given the index's
generation refuses a file of another run (`begin_outputs`); `capture_id`, the capture's id: a reader given the
capture's refuses a file of another capture (one written before the attribute was recorded has none, and its
generation ties it to its index); dataset `frames` (n, H, W[, C]) uint16, a Fletcher-32 checksum per chunk (older
files have none), holds value * `value_scale`, value in the source take's digital numbers (DN), `value_scale` 4
(1 for 15- and 16-bit cameras) so that a quarter DN of the sub-DN detail resampling and filtering create
survives, far below the sensor's noise; dataset `times_s` (n,), each frame's time; `bit_depth` of the source.
"""
from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any, ClassVar

import h5py
import numpy as np

from odsplat.spine.atomic import atomic_path, frame_compression, fsync_path, remove_stale_temporaries
from odsplat.spine.contract import CAPTURE_KEY, check_capture
from odsplat.spine.errors import InputError, SchemaError
from odsplat.spine.guard import link_error
from odsplat.spine.space import check_free, writing_h5

ALIGNED_KIND = "odsplat.aligned-take"        # sync's frames on the common grid
MAGNIFIED_KIND = "odsplat.magnified-take"    # processing's magnified frames
SCHEMA = 3   # 3: the generation attribute


# ------------------------------------------------------------------ a stage's outputs, committed together

def begin_outputs(index: Path, folder: Path, sized_like: Iterable[Path] = (), what: str = "its frames") -> str:
    """Start a run of a stage that writes a folder of frame files and then their index (sync, magnify): the old
    index goes first, durably, so a run killed from here on leaves no index and no reader takes its files as a
    set; temporaries of killed runs are removed. Returns the new run's generation id, for every file it writes.
    A link at the index or the folder is refused (`_plain_folder`): nothing is deleted through one.
    `sized_like`: the files the run's outputs will take about as much room as (its input takes: the same frames,
    resampled, compressed alike); a disk with less free (the space its old files held counted as free) is refused
    first, with one line (`space.check_free`)."""
    _plain_folder(folder)
    needed = sum(_size(p) for p in sized_like)
    if needed:
        old = sum(p.stat().st_size for p in _outputs(folder))
        check_free(folder, needed - old, what)
    if index.is_symlink():
        raise link_error(index)
    if index.exists():
        index.unlink()
        fsync_path(index.parent)
    remove_stale_temporaries(folder)
    return uuid.uuid4().hex[:16]


def _size(path: Path) -> int:
    try:
        return Path(path).stat().st_size
    except OSError:
        return 0


OUTPUT_PATTERNS = ("*.h5", "*.mp4")   # a stage's files in its folder: frames, and the videos made from them


def _plain_folder(folder: Path) -> None:
    """Refuse a stage's output folder that is a symbolic link (the capture was checked for links when opened;
    this is the last check before deleting in it)."""
    if folder.is_symlink():
        raise link_error(folder)


def _outputs(folder: Path) -> list[Path]:
    """The stage's own files in `folder`, by their naming scheme: plain `.h5` and `.mp4` files directly in it
    (a link among them is refused, never followed)."""
    _plain_folder(folder)
    if not folder.is_dir():
        return []
    found = [p for pattern in OUTPUT_PATTERNS for p in folder.glob(pattern)]
    for path in found:
        if path.is_symlink():
            raise link_error(path)
    return [p for p in found if p.is_file()]


def discard_outputs(folder: Path) -> None:
    """After a failed run: remove the folder's frame files and videos, which no index lists any more
    (`begin_outputs` removed the old one), so no reader finds half a set."""
    for path in _outputs(folder):
        path.unlink(missing_ok=True)


def prune_outputs(folder: Path, keep: Iterable[Path]) -> None:
    """After the index is written: remove the frame files and videos in `folder` it does not list (a take no
    longer selected, videos turned off, another run's leftovers). Paths are compared as written, no link
    followed."""
    keep = {os.path.normpath(os.path.abspath(p)) for p in keep}
    for path in _outputs(folder):
        if os.path.normpath(os.path.abspath(path)) not in keep:
            path.unlink()


def value_scale(bit_depth: int) -> float:
    """How much finer than a DN the stored values are: up to 2 extra bits, within 16."""
    return float(2 ** max(0, min(2, 16 - int(bit_depth))))


def to_stored(values_dn: np.ndarray, scale: float) -> np.ndarray:
    """DN (float) to the stored uint16: rounded, clipped to the 16-bit range."""
    return np.clip(np.rint(values_dn * scale), 0, 65535).astype(np.uint16)


@contextlib.contextmanager
def atomic_h5(path: str | Path) -> Iterator[h5py.File]:
    """An HDF5 file that appears at `path` only once written whole (`atomic.atomic_path`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, writing_h5(tmp, "w") as f:
        yield f


def create_frames(f: h5py.File, kind: str, *, frame_shape: tuple[int, ...], bit_depth: int, times_s: np.ndarray,
                  n_frames: int | None = None,
                  attrs: Mapping[str, Any] | None = None, capture_id: str | None = None) -> tuple[h5py.Dataset, float]:
    """The `frames` dataset (n_frames long, or growable from 0 when None) and `times_s`, with the file's
    attributes (`capture_id`: the capture's, which a reader given the capture checks); returns the dataset and its
    value scale. Chunks are one frame."""
    scale = value_scale(bit_depth)
    f.attrs.update(kind=kind, schema_version=SCHEMA, bit_depth=int(bit_depth), value_scale=scale,
                   **{k: v for k, v in (attrs or {}).items() if v is not None})
    if capture_id is not None:
        f.attrs[CAPTURE_KEY] = capture_id
    n = 0 if n_frames is None else n_frames
    ds = f.create_dataset("frames", shape=(n, *frame_shape), maxshape=(n_frames, *frame_shape), dtype=np.uint16,
                          chunks=(1, *frame_shape), fletcher32=True, **frame_compression())
    f.create_dataset("times_s", data=np.asarray(times_s, float))
    return ds, scale


# What h5py raises on a file that is not a whole HDF5 file of this layout: cut short or damaged (OSError; KeyError
# where an object's header is garbled; RuntimeError, ValueError, TypeError from a garbled attribute or type).
H5_ERRORS = (OSError, KeyError, RuntimeError, ValueError, TypeError)


class FrameFile:
    """Reads a derived frame file: frames as float32 in the source take's DN. Subclasses name the kind."""

    KIND: ClassVar[str] = ""
    KINDS: ClassVar[tuple[str, ...]] = ()  # when set, any of these kinds is accepted instead of KIND alone
    WHAT: ClassVar[str] = "derived frame file"
    MISSING: ClassVar[str] = "no such file"

    def __init__(self, path: str | Path, generation: str | None = None, capture_id: str | None = None):
        """`generation`: the index's (sync.json's, magnify.json's); a file of another run is refused.
        `capture_id`: the capture's; a file that records another capture's is refused. Whatever else is wrong with
        the file (empty, cut short, not HDF5, damaged, an attribute or dataset missing or of the wrong shape or
        type) is one line naming it."""
        self.path = Path(path)
        if self.path.is_file() and self.path.stat().st_size == 0:
            raise InputError(self.path, "empty file (0 bytes); run its stage again")
        try:
            self._file = h5py.File(self.path, "r")
        except FileNotFoundError:
            raise InputError(self.path, self.MISSING) from None
        except OSError as exc:
            raise InputError(self.path, f"cannot be opened as HDF5 ({' '.join(str(exc).split())}); run its stage "
                                        "again") from None
        try:
            self._check(generation, capture_id)
        except InputError:
            self._file.close()
            raise
        except H5_ERRORS as exc:
            self._file.close()
            raise InputError(self.path, f"not a readable {self.WHAT}, cut short or damaged ({type(exc).__name__}: "
                                        f"{' '.join(str(exc).split())[:200]}); run its stage again") from None

    def _check(self, generation: str | None, capture_id: str | None) -> None:
        attrs = self._file.attrs
        check_header(attrs, self.path, kinds=self.KINDS or (self.KIND,), schema=SCHEMA, what=self.WHAT,
                     generation=generation, capture_id=capture_id)
        scale = attrs.get("value_scale")
        if not isinstance(scale, (int, float, np.integer, np.floating)) or not 0 < float(scale) < np.inf:
            raise InputError(self.path, f"value_scale: expected a positive number, got {scale!r}; run its stage "
                                        "again")
        self.scale = float(scale)
        bits = attrs.get("bit_depth")
        if not isinstance(bits, (int, np.integer)) or not 1 <= bits <= 16:
            raise InputError(self.path, f"bit_depth: expected an integer from 1 to 16, got {bits!r}; run its stage "
                                        "again")
        frames, times = self._file.get("frames"), self._file.get("times_s")
        if not isinstance(frames, h5py.Dataset) or not isinstance(times, h5py.Dataset):
            raise InputError(self.path, f"not a whole {self.WHAT}: no {'frames' if times is not None else 'times_s'} "
                                        "dataset; run its stage again")
        if frames.ndim not in (3, 4) or frames.dtype != np.uint16:
            raise InputError(f"{self.path}: frames", f"expected (n, H, W[, C]) uint16, got {frames.shape} "
                                                     f"{frames.dtype}; run its stage again")
        if times.shape != frames.shape[:1] or times.dtype.kind != "f":
            raise InputError(f"{self.path}: times_s", f"expected ({frames.shape[0]},) floats, one per frame, got "
                                                      f"{times.shape} {times.dtype}; run its stage again")
        self._times = times[()]
        self._shape = tuple(frames.shape)

    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self._file.attrs)

    @property
    def n_frames(self) -> int:
        return self._shape[0]

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return self._shape[1:]

    @property
    def times_s(self) -> np.ndarray:
        return self._times.copy()

    def read_frames(self, start: int = 0, stop: int | None = None, spatial=None) -> np.ndarray:
        """Frames start..stop-1 as float32 DN; `spatial`: a map applied to each (as sync's aligned takes take it)."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        try:
            stored = self._file["frames"][start:stop]
        except H5_ERRORS as exc:
            raise InputError(self.path, f"frames {start}-{stop - 1}: unreadable, cut short or damaged "
                                        f"({' '.join(str(exc).split())[:200]}); run its stage again") from None
        frames = stored.astype(np.float32) / self.scale
        return frames if spatial is None or not len(frames) else np.stack([spatial(f) for f in frames])

    def iter_frames(self, chunk_frames: int = 16) -> Iterator[np.ndarray]:
        for k in range(0, self.n_frames, chunk_frames):
            yield self.read_frames(k, k + chunk_frames)

    def close(self) -> None:
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def check_header(attrs: Mapping[str, Any], path: Path, *, kinds: Iterable[str], schema: int, what: str,
                 generation: str | None, capture_id: str | None, again: str = "run its stage again") -> None:
    """A derived HDF5 file's header as its reader expects it: its kind, its schema, its capture's id and (when
    given) the generation its stage's index lists; otherwise one line naming the file, and `again` what to do."""
    kinds = tuple(kinds)
    if _text(attrs.get("kind")) not in kinds:
        article = "an" if what[:1] in "aeiou" else "a"
        raise SchemaError(path, f"not {article} {what} (kind {' or '.join(map(repr, kinds))} expected)")
    version = attrs.get("schema_version")
    if version != schema:
        newer = isinstance(version, (int, np.integer)) and version > schema
        raise SchemaError(path, f"{what} of schema {version}; this odsplat reads {schema} "
                                f"({'update odsplat' if newer else again})")
    check_capture(attrs.get(CAPTURE_KEY), path, capture_id)
    if generation is not None and _text(attrs.get("generation")) != generation:
        raise InputError(path, f"written by another run of its stage than its index lists (a run was interrupted): "
                               f"{again}")


def _text(value: Any) -> Any:
    return value.decode(errors="replace") if isinstance(value, bytes) else value


__all__ = ["FrameFile", "atomic_h5", "begin_outputs", "create_frames", "discard_outputs", "prune_outputs", "to_stored",
           "value_scale"]
