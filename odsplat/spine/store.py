"""The capture store: a directory with a manifest and one crash-safe HDF5 file per take.

Layout of a capture directory::

    capture.json          the manifest (odsplat.spine.manifest.Manifest)
    takes/<name>.h5       raw takes, written once: <name>.h5.partial while recording
    static/               optional photos of the still structure
    derived/              everything later stages write

Layout of a take file (schema 1.x), see docs/store.md::

    /frames               (T,H,W) or (T,H,W,3) uint8|uint16, one frame per chunk, Blosc-zstd + bitshuffle
    /frame_times_s        (T,) float64, frame exposure starts in the DAQ time base (NaN when unknown)
    /frame_counter        (T,) int64, the camera's own frame number (gaps reveal dropped frames)
    /daq/<channel>        (N,) float32 in SI units, attrs unit, kind
    /can/<node>/times_s   (M,) float64, each CAN sample's time in the DAQ time base (schema 1.1)
    /can/<node>/<channel> (M,) float32 in SI units at the node's own rate, NaN where a sample was lost
    /trigger, /qc         attributes, written when the take is finalised
"""
from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import re
import shutil
import uuid
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import IO, Any

import h5py
import hdf5plugin
import numpy as np

from odsplat.spine.contract import check, digest
from odsplat.spine.errors import IncompleteTakeError, InputError, OdsplatError, SchemaError, storage_error
from odsplat.spine.guard import lexically_inside, link_error, refuse_links
from odsplat.spine.manifest import (
    CAN_SOURCE_PREFIX,
    QC_KIND,
    QC_SCHEMA,
    SCHEMA_VERSION,
    ChannelInfo,
    Manifest,
    TakeRecord,
    check_name,
    check_schema,
    load_json,
    utc_now,
)
from odsplat.spine.paths import DerivedPaths
from odsplat.spine.space import CHUNK_CACHE_BYTES, Reserve, close_h5, process_alive, writing_h5
from odsplat.spine.timebase import resample_onto

log = logging.getLogger(__name__)

MANIFEST_NAME = "capture.json"
PARTIAL_SUFFIX = ".h5.partial"
CRASHED_SUFFIX = ".h5.crashed"
TAKE_SELECTIONS = ("accepted", "all")
QC_VERDICTS = ("accepted", "rejected")
_FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))


def frame_compression() -> Mapping[str, Any]:
    return hdf5plugin.Blosc(cname="zstd", clevel=3, shuffle=hdf5plugin.Blosc.BITSHUFFLE)


def fsync_path(path: Path) -> None:
    """fsync a file or a directory (the latter makes a rename durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_TEMPORARY = re.compile(r"\..+\.(?P<pid>\d+)\.tmp(\.\w+)?")   # what atomic_path names its temporaries


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside `path` to write; on a clean exit the file is fsynced and renamed over `path` (and
    the directory fsynced), on an error removed. A crash leaves either the old file or the new one, never half.
    `suffix` ends the temporary's name, for writers that choose a format by it (OpenCV's mp4: ".mp4").
    A folder that is a symbolic link is refused (nothing is written through a link), and whatever lies at the
    temporary's name (a dead process's file with this pid, or a link planted there) is removed first, so the
    writer creates a new plain file."""
    path = Path(path)
    if path.parent.is_symlink():
        raise link_error(path.parent)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    if os.path.lexists(tmp):
        tmp.unlink()
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Remove the temporaries `atomic_path` leaves when its writer is killed (`.NAME.PID.tmp[SUFFIX]`, in `folder`
    and below) whose process is gone; a live writer's are left alone. Links are neither followed nor removed, a
    linked `folder` is not walked. Returns what was removed."""
    folder = Path(folder)
    removed: list[Path] = []
    if folder.is_symlink() or not folder.is_dir():
        return removed
    for here, _dirs, files in os.walk(folder, followlinks=False):
        for name in files:
            tmp = Path(here) / name
            match = _TEMPORARY.fullmatch(name)
            if match is None or tmp.is_symlink() or process_alive(int(match["pid"])):
                continue
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    if removed:
        log.info("removed %d temporaries of killed runs under %s", len(removed), folder)
    return removed


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside `path`, made durable and renamed over `path` on a clean exit (`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, mode) as fh:
        yield fh


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to `path` so that a crash leaves either the old file or the new one, never half."""
    with atomic_open(path, "w") as fh:
        fh.write(text)


@dataclass(frozen=True)
class TriggerInfo:
    """Where the trigger lies in a take: DAQ sample, samples kept before it, and the camera's trigger frame."""

    trigger_sample: int | None = None
    pretrigger_samples: int | None = None
    camera_trigger_frame: int | None = None
    trigger_time_s: float | None = None


@dataclass(frozen=True)
class QCInfo:
    status: str = "unchecked"
    flags: tuple[str, ...] = ()
    notes: str = ""


@dataclass(frozen=True)
class RecoveryReport:
    """What `recover_partial` did with one unfinished take file."""

    name: str
    recovered: bool
    n_frames: int
    n_samples: int
    message: str
    path: Path | None = None


class TakeWriter:
    """Records one take into `<name>.h5.partial` (SWMR, flushed per frame and per block), then finalises it.

    All datasets are created up front, because an HDF5 SWMR writer may only append. `channels` may mix the
    DAQ's channels (`source` "daq", appended with `append_samples`) and CAN nodes' (`source` "can:NODE", each
    node a group of its own at its own rate, appended with `append_can_samples`).
    `finalize()` writes the trigger and QC attributes, verifies, fsyncs and renames to `<name>.h5`.
    """

    def __init__(
        self,
        final_path: str | Path,
        *,
        frame_shape: Sequence[int] | None,
        dtype: Any = np.uint16,
        bit_depth: int | None = None,
        channels: Sequence[ChannelInfo] = (),
        daq_sample_rate_hz: float | None = None,
        daq_t0_s: float = 0.0,
        attrs: Mapping[str, Any] | None = None,
        swmr: bool = True,
        on_finalize: Any = None,
    ):
        self.final_path = Path(final_path)
        self.partial_path = self.final_path.with_name(self.final_path.name[: -len(".h5")] + PARTIAL_SUFFIX)
        if self.final_path.exists():
            raise OdsplatError(f"{self.final_path}: take already exists; raw takes are written once")
        if self.partial_path.exists():
            raise OdsplatError(f"{self.partial_path}: an unfinished take is in the way; run `odsplat recover` first")
        self.name = self.final_path.name[: -len(".h5")]
        self.dtype = np.dtype(dtype)
        if frame_shape is not None and self.dtype not in _FRAME_DTYPES:
            raise InputError(self.name, f"frames must be uint8 or uint16; got {self.dtype}")
        self.frame_shape = tuple(int(s) for s in frame_shape) if frame_shape is not None else None
        if self.frame_shape is not None and not (
            len(self.frame_shape) == 2 or (len(self.frame_shape) == 3 and self.frame_shape[2] == 3)
        ):
            raise InputError(self.name, f"frame shape must be (H, W) or (H, W, 3); got {self.frame_shape}")
        self.bit_depth = int(bit_depth or self.dtype.itemsize * 8)
        if self.bit_depth > self.dtype.itemsize * 8:
            raise InputError(self.name, f"bit depth {self.bit_depth} does not fit in {self.dtype}")
        self.channels = [c for c in channels if c.can_node is None]
        self.can_channels: dict[str, list[ChannelInfo]] = {}
        for c in channels:
            if c.can_node is not None:
                self.can_channels.setdefault(c.can_node, []).append(c)
        if self.channels and not daq_sample_rate_hz:
            raise InputError(self.name, "DAQ channels need a sample rate")
        self._on_finalize = on_finalize
        self._trigger = TriggerInfo()
        self._qc = QCInfo()
        self._n_frames = 0
        self._n_samples = {c.name: 0 for c in self.channels}
        self._n_can = {node: 0 for node in self.can_channels}
        self._closed = False
        self._view = (attrs or {}).get("view")

        self.partial_path.parent.mkdir(parents=True, exist_ok=True)
        self._reserve = Reserve(self.partial_path.parent)   # room to close the file on a full disk (spine.space)
        try:
            f = h5py.File(self.partial_path, "w", libver="latest", rdcc_nbytes=CHUNK_CACHE_BYTES)
        except BaseException:
            self._reserve.release()
            raise
        self._file = f
        f.attrs.update(
            {
                "odsplat_schema": SCHEMA_VERSION,
                "kind": "take",
                "take": self.name,
                "created_utc": utc_now(),
                "complete": False,
                "recovered": False,
            }
        )
        for key, value in (attrs or {}).items():
            f.attrs[key] = value if not isinstance(value, (dict, list)) else json.dumps(value)
        if self.frame_shape is not None:
            self._frames = f.create_dataset(
                "frames",
                shape=(0, *self.frame_shape),
                maxshape=(None, *self.frame_shape),
                chunks=(1, *self.frame_shape),
                dtype=self.dtype,
                fletcher32=True,
                **frame_compression(),
            )
            self._frames.attrs["bit_depth"] = self.bit_depth
            self._times = f.create_dataset("frame_times_s", shape=(0,), maxshape=(None,), chunks=(4096,), dtype="f8",
                                           fletcher32=True)
            self._counter = f.create_dataset("frame_counter", shape=(0,), maxshape=(None,), chunks=(4096,), dtype="i8",
                                             fletcher32=True)
        daq = f.create_group("daq")
        daq.attrs["sample_rate_hz"] = float(daq_sample_rate_hz or 0.0)
        daq.attrs["t0_s"] = float(daq_t0_s)
        daq.attrs["channel_order"] = json.dumps([c.name for c in self.channels])
        self._daq = {}
        for ch in self.channels:
            ch.validate(f"{self.name}: channel {ch.name!r}")
            ds = daq.create_dataset(ch.name, shape=(0,), maxshape=(None,), chunks=(16384,), dtype="f4", fletcher32=True)
            ds.attrs["unit"] = ch.unit
            ds.attrs["kind"] = ch.kind
            ds.attrs["info"] = json.dumps(asdict(ch))
            self._daq[ch.name] = ds
        self._can: dict[str, dict[str, h5py.Dataset]] = {}
        if self.can_channels:
            self._create_can(f)
        if swmr:
            f.swmr_mode = True

    def _create_can(self, f: h5py.File) -> None:
        can = f.create_group("can")
        can.attrs["node_order"] = json.dumps(list(self.can_channels))
        for node, chans in self.can_channels.items():
            for ch in chans:
                ch.validate(f"{self.name}: channel {ch.name!r}")
            rates = {c.sample_rate_hz for c in chans}
            if len(rates) != 1:
                raise InputError(f"{self.name}: CAN node {node!r}",
                                 f"its channels disagree on the sample rate: {sorted(rates)}")
            g = can.create_group(node)
            g.attrs["sample_rate_hz"] = float(rates.pop())
            g.attrs["source"] = CAN_SOURCE_PREFIX + node
            g.attrs["channel_order"] = json.dumps([c.name for c in chans])
            sets = {"times_s": g.create_dataset("times_s", shape=(0,), maxshape=(None,), chunks=(4096,), dtype="f8",
                                                fletcher32=True)}
            for ch in chans:
                if ch.name in self._daq or ch.name in sets or any(ch.name in d for d in self._can.values()):
                    raise InputError(f"{self.name}: channel {ch.name!r}", "the name is used twice")
                ds = g.create_dataset(ch.name, shape=(0,), maxshape=(None,), chunks=(4096,), dtype="f4",
                                      fletcher32=True)
                ds.attrs["unit"] = ch.unit
                ds.attrs["kind"] = ch.kind
                ds.attrs["info"] = json.dumps(asdict(ch))
                sets[ch.name] = ds
            self._can[node] = sets

    # -- recording -------------------------------------------------------------------------

    @property
    def n_frames(self) -> int:
        return self._n_frames

    def append_frames(
        self,
        frames: np.ndarray,
        times_s: Sequence[float] | np.ndarray | None = None,
        counter: Sequence[int] | np.ndarray | None = None,
    ) -> None:
        """Append one frame (H,W[,3]) or a block (n,H,W[,3]); each frame is flushed before the next."""
        if self.frame_shape is None:
            raise OdsplatError(f"{self.name}: this take was created without frames")
        frames = np.asarray(frames)
        if frames.shape == self.frame_shape:
            frames = frames[None]
        if frames.shape[1:] != self.frame_shape:
            raise InputError(self.name, f"frame shape {frames.shape[1:]} differs from the take's {self.frame_shape}")
        if frames.dtype != self.dtype:
            raise InputError(self.name, f"frame dtype {frames.dtype} differs from the take's {self.dtype}")
        n = len(frames)
        times = np.full(n, np.nan) if times_s is None else np.asarray(times_s, dtype="f8").reshape(n)
        counts = np.arange(self._n_frames, self._n_frames + n) if counter is None else np.asarray(counter).reshape(n)
        for i in range(n):
            k = self._n_frames
            self._frames.resize(k + 1, axis=0)
            self._frames[k] = frames[i]
            self._frames.flush()
            # The times and counter are written after the pixels: their length is the count of
            # frames whose pixels reached the file, which is what recovery trusts.
            self._times.resize(k + 1, axis=0)
            self._times[k] = times[i]
            self._counter.resize(k + 1, axis=0)
            self._counter[k] = counts[i]
            self._times.flush()
            self._counter.flush()
            self._n_frames = k + 1

    def append_samples(self, block: Mapping[str, np.ndarray]) -> None:
        """Append a block of samples for every channel (same length for all, in SI units)."""
        if set(block) != set(self._daq):
            raise InputError(self.name, f"sample block has channels {sorted(block)}; expected {sorted(self._daq)}")
        lengths = {len(v) for v in block.values()}
        if len(lengths) != 1:
            by_channel = {k: len(v) for k, v in block.items()}
            raise InputError(self.name, f"sample block channels differ in length: {by_channel}")
        for name, values in block.items():
            ds = self._daq[name]
            k = self._n_samples[name]
            n = len(values)
            ds.resize(k + n, axis=0)
            ds[k:] = np.asarray(values, dtype="f4")
            ds.flush()
            self._n_samples[name] = k + n

    def append_can_samples(self, node: str, times_s: np.ndarray, block: Mapping[str, np.ndarray]) -> None:
        """Append consecutive samples of one CAN node: their times in the DAQ time base and every channel of the
        node (SI units, NaN where lost). The times are written after the values, so that their length counts the
        samples whose values reached the file, which is what recovery trusts."""
        if node not in self._can:
            raise InputError(f"{self.name}: CAN node {node!r}", f"not in this take; its nodes are {list(self._can)}")
        sets = self._can[node]
        names = [c.name for c in self.can_channels[node]]
        if set(block) != set(names):
            raise InputError(f"{self.name}: CAN node {node!r}", f"sample block has channels {sorted(block)}; "
                             f"expected {sorted(names)}")
        times = np.asarray(times_s, dtype="f8").reshape(-1)
        n = len(times)
        bad = {k: len(v) for k, v in block.items() if len(v) != n}
        if bad:
            raise InputError(f"{self.name}: CAN node {node!r}", f"{n} times but channel lengths {bad}")
        k = self._n_can[node]
        for name in names:
            ds = sets[name]
            ds.resize(k + n, axis=0)
            ds[k:] = np.asarray(block[name], dtype="f4")
            ds.flush()
        ds = sets["times_s"]
        ds.resize(k + n, axis=0)
        ds[k:] = times
        ds.flush()
        self._n_can[node] = k + n

    def set_trigger(self, trigger: TriggerInfo) -> None:
        self._trigger = trigger

    def set_qc(self, qc: QCInfo) -> None:
        if qc.status not in ("unchecked", "accepted", "rejected"):
            raise InputError(self.name, f"QC status must be unchecked, accepted or rejected; got {qc.status!r}")
        self._qc = qc

    # -- finishing -------------------------------------------------------------------------

    def finalize(self, *, recovered: bool = False) -> TakeRecord:
        """Write trigger and QC, verify, fsync and rename to the final name. Returns the manifest record."""
        self._closed = True
        close_h5(self._file, self._reserve)
        with writing_h5(self.partial_path, "r+") as f:
            trig = f.require_group("trigger")
            for key, value in asdict(self._trigger).items():
                trig.attrs[key] = _none_to_nan(value)
            qc = f.require_group("qc")
            qc.attrs["status"] = self._qc.status
            qc.attrs["flags"] = json.dumps(list(self._qc.flags))
            qc.attrs["notes"] = self._qc.notes
            f.attrs["complete"] = not recovered
            f.attrs["recovered"] = recovered
            f.attrs["finalized_utc"] = utc_now()
        self._verify()
        fsync_path(self.partial_path)
        os.replace(self.partial_path, self.final_path)
        fsync_path(self.final_path.parent)
        record = TakeRecord(
            name=self.name,
            file=f"takes/{self.final_path.name}",
            view=_view_or_none(self._view),
            status="recovered" if recovered else "complete",
            qc=self._qc.status,
            n_frames=self._n_frames,
            n_samples=max(self._n_samples.values(), default=0),
            created_utc=utc_now(),
        )
        log.info("take %s finalised: %d frames, %d samples", self.name, record.n_frames, record.n_samples)
        if self._on_finalize is not None:
            self._on_finalize(record)
        return record

    def close_unfinished(self) -> None:
        """Close without finalising: the `.partial` file stays for `recover_partial` to deal with."""
        if not self._closed:
            self._closed = True
            try:
                close_h5(self._file, self._reserve)
            except (OSError, RuntimeError) as exc:   # a full disk: what was flushed stays, for `recover_partial`
                log.warning("%s: not closed cleanly (%s); `odsplat recover` keeps what was flushed",
                            self.partial_path, " ".join(str(exc).split())[:200])

    def _verify(self) -> None:
        with h5py.File(self.partial_path, "r") as f:
            if self.frame_shape is not None:
                n = (f["frames"].shape[0], f["frame_times_s"].shape[0], f["frame_counter"].shape[0])
                if len(set(n)) != 1 or n[0] != self._n_frames:
                    raise OdsplatError(f"{self.partial_path}: verification failed, frame datasets hold {n}")
                if self._n_frames:
                    f["frames"][self._n_frames - 1]  # decompresses the last chunk
            for name, k in self._n_samples.items():
                if f["daq"][name].shape[0] != k:
                    raise OdsplatError(f"{self.partial_path}: verification failed for channel {name}")
            for node, k in self._n_can.items():
                if any(f["can"][node][name].shape[0] != k for name in self._can[node]):
                    raise OdsplatError(f"{self.partial_path}: verification failed for CAN node {node}")

    def __enter__(self) -> TakeWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        # An exception leaves the partial file closed and in place: recorded data is never deleted.
        self.close_unfinished()


def _none_to_nan(value: Any) -> Any:
    return np.nan if value is None else value


def _nan_to_none(value: Any) -> Any:
    if value is None:
        return None
    if isinstance(value, (float, np.floating)) and np.isnan(value):
        return None
    return value.item() if isinstance(value, np.generic) else value


def _maybe_int(value: Any) -> int | None:
    value = _nan_to_none(value)
    return None if value is None or value == "" else int(value)


def _view_or_none(value: Any) -> int | None:
    """A take file stores "no viewpoint" as -1 (HDF5 attributes cannot be None)."""
    view = _maybe_int(value)
    return None if view is None or view < 0 else view


def _ranges(indices: Sequence[int]) -> str:
    """[3, 4, 5, 9] -> "3-5, 9" (inclusive ranges)."""
    runs: list[list[int]] = []
    for k in sorted(indices):
        if runs and k == runs[-1][1] + 1:
            runs[-1][1] = k
        else:
            runs.append([k, k])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def damaged_chunks(ds: h5py.Dataset, start: int = 0, stop: int | None = None) -> list[tuple[int, int]]:
    """The chunks along the first axis of `ds` within [start, stop) that cannot be read back (a Fletcher-32 mismatch,
    a chunk that does not decode, or one beyond the end of a truncated file), as (first, stop) index pairs."""
    n = ds.shape[0] if ds.shape else 0
    stop = n if stop is None else min(stop, n)
    step = ds.chunks[0] if ds.chunks else max(n, 1)
    bad = []
    for a in range(start - start % step, stop, step):
        b = min(a + step, n)
        try:
            ds[a:b]
        except OSError:
            bad.append((max(a, start), min(b, stop)))
    return bad


def damage_text(ds: h5py.Dataset, bad: Sequence[tuple[int, int]]) -> str:
    """What a reader says of damaged chunks: which frames or samples, and why they cannot be trusted."""
    unit = "frames" if ds.name in ("/frames", "/frame_times_s", "/frame_counter") else "samples"
    where = _ranges([k for a, b in bad for k in range(a, b)])
    why = "their checksum (Fletcher-32) fails" if ds.fletcher32 else "they cannot be decoded (no checksum stored)"
    return f"{unit} {where} of {ds.shape[0]} damaged: {why}"


class CheckedDataset:
    """A raw take dataset read through its per-chunk checksums: a read that meets a damaged chunk raises one
    `InputError` naming the take file, the dataset and the frames or samples, never h5py's OSError. Everything
    else (shape, dtype, attrs, chunks, id) is the dataset's own."""

    def __init__(self, ds: h5py.Dataset, path: Path):
        self._ds = ds
        self._path = path

    def __getitem__(self, selection: Any) -> np.ndarray:
        try:
            return self._ds[selection]
        except OSError:
            first = selection[0] if isinstance(selection, tuple) and selection else selection
            n = self._ds.shape[0]
            if isinstance(first, slice):
                start, stop, _ = first.indices(n)
            elif isinstance(first, (int, np.integer)):
                start = int(first) % n if n else 0
                stop = start + 1
            else:
                start, stop = 0, n
            bad = damaged_chunks(self._ds, start, max(stop, start + 1)) or damaged_chunks(self._ds)
            what = damage_text(self._ds, bad) if bad else "cannot be read"
            raise InputError(f"{self._path}: {self._ds.name}", what) from None

    def __len__(self) -> int:
        return len(self._ds)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._ds, name)


class TakeReader:
    """Reads a finalised take file; frames are streamed in chunks, never loaded whole. Every read of a raw dataset
    goes through its checksums (`CheckedDataset`)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if self.path.name.endswith(PARTIAL_SUFFIX):
            raise IncompleteTakeError(self.path, "this take was never finalised; run `odsplat recover` on its capture")
        try:
            self._file = h5py.File(self.path, "r")
        except FileNotFoundError:
            raise InputError(self.path, "no such take file") from None
        except OSError as exc:
            raise InputError(self.path, f"cannot be opened as HDF5 ({exc})") from None
        attrs = self._file.attrs
        if attrs.get("kind") != "take" or "odsplat_schema" not in attrs:
            self._file.close()
            raise SchemaError(self.path, "not an odsplat take file (no odsplat_schema attribute)")
        try:
            check_schema(attrs["odsplat_schema"], where=f"{self.path}: odsplat_schema")
        except SchemaError:
            self._file.close()
            raise
        if not attrs.get("complete") and not attrs.get("recovered"):
            self._file.close()
            raise IncompleteTakeError(self.path, "the take was not finalised")
        name = attrs.get("take", self.path.stem)
        try:   # the name becomes derived file names (derived/sync/NAME.h5): checked here as on import
            self.name = check_name(name.decode() if isinstance(name, bytes) else name, f"{self.path}: attribute take")
        except InputError:
            self._file.close()
            raise
        self.recovered = bool(attrs.get("recovered"))

    # -- metadata ---------------------------------------------------------------------------

    @property
    def attrs(self) -> dict[str, Any]:
        return {k: _nan_to_none(v) for k, v in self._file.attrs.items()}

    @property
    def view(self) -> int | None:
        return _view_or_none(self._file.attrs.get("view"))

    @property
    def has_frames(self) -> bool:
        return "frames" in self._file

    @property
    def frames(self) -> CheckedDataset:
        """The frames dataset, read through its checksums: index it to read a slice, it is never read whole here."""
        if not self.has_frames:
            raise InputError(self.path, "this take holds no frames")
        return self.dataset("frames")

    def dataset(self, key: str) -> CheckedDataset:
        """A raw dataset of the take (`frames`, `daq/NAME`, `can/NODE/times_s`, ...) read through its checksums."""
        return CheckedDataset(self._file[key], self.path)

    @property
    def n_frames(self) -> int:
        return self.frames.shape[0] if self.has_frames else 0

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self.frames.shape[1:])

    @property
    def bit_depth(self) -> int:
        return int(self.frames.attrs["bit_depth"])

    @property
    def fps(self) -> float | None:
        return _nan_to_none(self._file.attrs.get("fps"))

    @property
    def frame_times_s(self) -> np.ndarray:
        return self.dataset("frame_times_s")[:] if self.has_frames else np.empty(0)

    @property
    def frame_counter(self) -> np.ndarray:
        return self.dataset("frame_counter")[:] if self.has_frames else np.empty(0, dtype="i8")

    @property
    def sample_rate_hz(self) -> float:
        return float(self._file["daq"].attrs["sample_rate_hz"])

    @property
    def daq_t0_s(self) -> float:
        return float(self._file["daq"].attrs["t0_s"])

    @property
    def channel_names(self) -> list[str]:
        return json.loads(self._file["daq"].attrs["channel_order"])

    @property
    def n_samples(self) -> int:
        names = self.channel_names
        return self._file["daq"][names[0]].shape[0] if names else 0

    def channel_info(self, name: str) -> ChannelInfo:
        """A DAQ or CAN channel's manifest entry, as recorded in the take."""
        ds = self._file["can"][self._can_node_of(name)][name] if name in self._can_index else self._channel(name)
        return ChannelInfo(**json.loads(ds.attrs["info"]))

    def channels_of_kind(self, kind: str) -> list[str]:
        """The DAQ channels of one kind (`manifest.CHANNEL_KINDS`: force, acceleration, ttl, ...), in order."""
        return [n for n in self.channel_names if self.channel_info(n).kind == kind]

    def channel(self, name: str) -> np.ndarray:
        """A channel's samples in SI units on the DAQ's sample grid (`daq_t0_s + k / sample_rate_hz`).

        A DAQ channel: its samples (float32). A CAN channel: its samples resampled onto that grid
        (`odsplat.spine.timebase.resample_onto`: band-limited, linear within 16 CAN samples of the record's ends or of
        a lost sample, NaN outside the CAN record), so that it can be used as a DAQ channel; its own samples
        are `can_channel(name)`."""
        if name in self._can_index:
            times, values = self.can_channel(name)
            node = self._can_node_of(name)
            grid = self.daq_t0_s + np.arange(self.n_samples) / self.sample_rate_hz
            rate = self.can_sample_rate_hz(node)
            if len(times) > 1 and np.max(np.abs(times - (times[0] + np.arange(len(times)) / rate))) < 1e-3 / rate:
                return resample_onto(values, float(times[0]), rate, grid).astype(np.float32)
            log.warning("%s: CAN node %s's times are not regular at %g Hz; %s is interpolated linearly",
                        self.path, node, rate, name)
            return np.interp(grid, times, values, left=np.nan, right=np.nan).astype(np.float32)
        return self._channel(name)[:]

    def _channel(self, name: str) -> CheckedDataset:
        if name not in self.channel_names:
            raise InputError(self.path,
                             f"no DAQ channel {name!r} (nor a CAN channel of that name); the take has "
                             f"{self.channel_names + self.can_channel_names}")
        return self.dataset(f"daq/{name}")

    # -- CAN nodes (schema 1.1) ---------------------------------------------------------------

    @property
    def can_nodes(self) -> list[str]:
        """The CAN nodes recorded in this take (each a group /can/NODE at its own rate); [] in older takes."""
        return json.loads(self._file["can"].attrs["node_order"]) if "can" in self._file else []

    @property
    def can_channel_names(self) -> list[str]:
        return list(self._can_index)

    def can_sample_rate_hz(self, node: str) -> float:
        return float(self._can_group(node).attrs["sample_rate_hz"])

    def can_times_s(self, node: str) -> np.ndarray:
        """The node's sample times in the DAQ time base (float64)."""
        self._can_group(node)
        return self.dataset(f"can/{node}/times_s")[:]

    def can_channel(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """A CAN channel's own samples: (times in the DAQ time base, float64; values in SI units, float32, NaN
        where a sample was lost)."""
        node = self._can_node_of(name)
        return self.dataset(f"can/{node}/times_s")[:], self.dataset(f"can/{node}/{name}")[:]

    @functools.cached_property
    def _can_index(self) -> dict[str, str]:
        """CAN channel name -> its node."""
        return {name: node for node in self.can_nodes
                for name in json.loads(self._file["can"][node].attrs["channel_order"])}

    def _can_node_of(self, name: str) -> str:
        try:
            return self._can_index[name]
        except KeyError:
            raise InputError(self.path, f"no CAN channel {name!r}; the take has {self.can_channel_names}") from None

    def _can_group(self, node: str) -> h5py.Group:
        if node not in self.can_nodes:
            raise InputError(self.path, f"no CAN node {node!r}; the take has {self.can_nodes}")
        return self._file["can"][node]

    @property
    def trigger(self) -> TriggerInfo:
        a = self._file["trigger"].attrs
        return TriggerInfo(
            trigger_sample=_maybe_int(a.get("trigger_sample")),
            pretrigger_samples=_maybe_int(a.get("pretrigger_samples")),
            camera_trigger_frame=_maybe_int(a.get("camera_trigger_frame")),
            trigger_time_s=_nan_to_none(a.get("trigger_time_s")),
        )

    @property
    def qc(self) -> QCInfo:
        a = self._file["qc"].attrs
        return QCInfo(status=str(a["status"]), flags=tuple(json.loads(a["flags"])), notes=str(a["notes"]))

    @property
    def size_bytes(self) -> int:
        return self.path.stat().st_size

    # -- frames -----------------------------------------------------------------------------

    def read_frames(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        if not 0 <= start <= stop:
            raise InputError(self.path, f"frame range {start}:{stop} outside 0:{self.n_frames}")
        return self.frames[start:stop]

    def iter_frames(self, chunk_frames: int = 64, start: int = 0, stop: int | None = None) -> Iterator[np.ndarray]:
        """Yield blocks of at most `chunk_frames` frames; memory stays bounded by one block."""
        stop = self.n_frames if stop is None else min(stop, self.n_frames)
        for k in range(start, stop, chunk_frames):
            yield self.frames[k : min(k + chunk_frames, stop)]

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> TakeReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def recover_partial(partial_path: str | Path, *, chunk_frames: int = 64) -> RecoveryReport:
    """Turn an unfinished take into a finalised one holding every frame and sample that was flushed.

    The unfinished file is kept, renamed to `<name>.h5.crashed`; the recovered take is marked
    `recovered` with a QC flag, so it is never mistaken for a complete one.
    """
    partial_path = Path(partial_path)
    name = partial_path.name[: -len(PARTIAL_SUFFIX)]
    final_path = partial_path.with_name(name + ".h5")
    crashed_path = partial_path.with_name(name + CRASHED_SUFFIX)
    tmp_final = final_path.with_name(name + ".recovering.h5")
    half_made = (tmp_final, tmp_final.with_name(name + ".recovering" + PARTIAL_SUFFIX))   # our copy, not data
    try:
        src = h5py.File(partial_path, "r", swmr=True)
    except BlockingIOError as exc:  # HDF5's file lock: a writer still has it open
        return RecoveryReport(name, False, 0, 0, f"{partial_path}: in use by another process (a capture still "
                              f"recording?), left in place ({exc})")
    except OSError as exc:
        return _set_aside(partial_path, crashed_path, f"unreadable as HDF5 ({exc}); a writer killed while creating "
                          "the file leaves it so, before any frame or sample is written")
    writer = None
    with src:
        try:
            check_schema(src.attrs.get("odsplat_schema", "missing"), where=str(partial_path))
            has_frames = "frames" in src
            n_frames = (min(src["frames"].shape[0], src["frame_counter"].shape[0], src["frame_times_s"].shape[0])
                        if has_frames else 0)
            daq = src["daq"]
            names = json.loads(daq.attrs["channel_order"])
            n_samples = min((daq[n].shape[0] for n in names), default=0)
            channels = [ChannelInfo(**json.loads(daq[n].attrs["info"])) for n in names]
            can = {}  # node -> (its channel names, samples whose values and times were both flushed)
            if "can" in src:
                for node in json.loads(src["can"].attrs["node_order"]):
                    g = src["can"][node]
                    node_names = json.loads(g.attrs["channel_order"])
                    channels += [ChannelInfo(**json.loads(g[n].attrs["info"])) for n in node_names]
                    can[node] = (node_names, min(g[n].shape[0] for n in ["times_s", *node_names]))
            attrs = {k: v for k, v in src.attrs.items() if k not in ("odsplat_schema", "kind", "complete", "recovered")}
            for leftover in half_made:
                leftover.unlink(missing_ok=True)
            writer = TakeWriter(
                tmp_final,
                frame_shape=src["frames"].shape[1:] if has_frames else None,
                dtype=src["frames"].dtype if has_frames else np.uint16,
                bit_depth=int(src["frames"].attrs["bit_depth"]) if has_frames else None,
                channels=channels,
                daq_sample_rate_hz=float(daq.attrs["sample_rate_hz"]) or None,
                daq_t0_s=float(daq.attrs["t0_s"]),
                attrs=attrs,
                swmr=False,
            )
            for k in range(0, n_frames, chunk_frames):
                stop = min(k + chunk_frames, n_frames)
                writer.append_frames(src["frames"][k:stop], src["frame_times_s"][k:stop], src["frame_counter"][k:stop])
            if names and n_samples:
                writer.append_samples({n: daq[n][:n_samples] for n in names})
            for node, (node_names, m) in can.items():
                if m:
                    g = src["can"][node]
                    writer.append_can_samples(node, g["times_s"][:m], {n: g[n][:m] for n in node_names})
        except (OSError, KeyError, ValueError, RuntimeError) as exc:
            if writer is not None:
                writer.close_unfinished()
            for leftover in half_made:
                leftover.unlink(missing_ok=True)
            src.close()
            storage = storage_error(exc)
            if storage is not None:   # the disk, not the take: left as it is, to recover once there is room
                raise storage from None
            what = ("its writer stopped while creating it, before any frame or sample was written"
                    if isinstance(exc, KeyError) else "could not be copied")
            return _set_aside(partial_path, crashed_path, f"{what} ({type(exc).__name__}: {exc})")
    message = (f"recovered after a crash: {n_frames} frames and {n_samples} samples were flushed before the writer "
               "stopped")
    writer.set_qc(QCInfo(status="unchecked", flags=("recovered",), notes=message))
    writer.finalize(recovered=True)
    os.replace(partial_path, crashed_path)
    os.replace(tmp_final, final_path)
    fsync_path(final_path.parent)
    log.warning("%s: %s", partial_path, message)
    return RecoveryReport(name, True, n_frames, n_samples, message, final_path)


def _set_aside(partial_path: Path, crashed_path: Path, why: str) -> RecoveryReport:
    """Keep an unfinished take that cannot be recovered as `<name>.h5.crashed`, so no resume trips over it again."""
    os.replace(partial_path, crashed_path)
    fsync_path(crashed_path.parent)
    message = f"not recovered: {why}; the file is kept as {crashed_path.name}"
    log.warning("%s: %s", partial_path, message)
    return RecoveryReport(crashed_path.name[: -len(CRASHED_SUFFIX)], False, 0, 0, message, crashed_path)


class Capture:
    """A capture directory: the manifest, the raw takes and the derived results."""

    def __init__(self, root: str | Path, manifest: Manifest, derived: str | Path | None = None):
        self.root = Path(root)
        self.manifest = manifest
        # Every derived path comes from this registry; `derived` sends them elsewhere (the capture stays as it is).
        self.paths = DerivedPaths(Path(derived) if derived is not None else self.root / "derived")
        if derived is not None:
            self._check_derived_elsewhere(Path(derived))

    def _check_derived_elsewhere(self, derived: Path) -> None:
        """A derived folder given apart from the capture may lie anywhere but among its raw data (takes/, static/,
        the capture's own top folder) or above the capture: a stage's clean-up deletes files in it."""
        if lexically_inside(self.root, derived) and not lexically_inside(self.root / "derived", derived):
            parts = Path(os.path.relpath(os.path.abspath(derived), os.path.abspath(self.root))).parts
            raise InputError(derived, f"inside the capture's {parts[0] + '/' if parts else 'top folder'}; derived "
                                      "files go to derived/ or a folder outside the capture")
        if lexically_inside(derived, self.root):
            raise InputError(derived, f"holds the capture {self.root}; derived files go to a folder of their own")

    def refuse_links(self) -> None:
        """Refuse (one line) a capture that holds a symbolic link anywhere (capture.json, takes/, static/, derived/,
        or the derived folder given apart): odsplat goes through none (`guard`)."""
        outside = self.paths.root if not lexically_inside(self.root, self.paths.root) else None
        refuse_links(self.root)
        if outside is not None:
            refuse_links(outside)

    @classmethod
    def create(cls, root: str | Path, manifest: Manifest) -> Capture:
        root = Path(root)
        if (root / MANIFEST_NAME).exists():
            raise OdsplatError(f"{root}: a capture exists here already")
        manifest.validate(str(root / MANIFEST_NAME))
        if not manifest.capture_id:
            manifest.capture_id = uuid.uuid4().hex
        for sub in ("takes", "static", "derived"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        capture = cls(root, manifest)
        capture.save_manifest()
        return capture

    @classmethod
    def open(cls, root: str | Path, *, derived: str | Path | None = None) -> Capture:
        """Open a capture; `derived` (a folder) takes every derived file instead of the capture's `derived/`."""
        root = Path(root)
        if not root.is_dir():
            raise InputError(root, "no such capture directory")
        capture = cls(root, Manifest.load(root / MANIFEST_NAME), derived)
        capture.refuse_links()
        return capture

    @property
    def id(self) -> str:
        """The capture's identity, recorded in every derived file: its manifest's id (older captures: a hash of
        their name and creation time)."""
        return self.manifest.capture_id or digest([self.manifest.name, self.manifest.created_utc])

    @property
    def takes_dir(self) -> Path:
        return self.root / "takes"

    @property
    def derived_dir(self) -> Path:
        """The root of the derived files (`paths.root`); reading it creates nothing."""
        return self.paths.root

    @property
    def static_dir(self) -> Path:
        return self.root / "static"

    def save_manifest(self) -> None:
        atomic_write_text(self.root / MANIFEST_NAME, self.manifest.to_json())

    # -- takes ------------------------------------------------------------------------------

    def take_names(self) -> list[str]:
        return [t.name for t in self.manifest.takes]

    def select_takes(self, which: str = "accepted") -> list[TakeRecord]:
        """The takes a stage works on, the one rule for every stage: the complete (or recovered) takes that QC
        accepted, or with "all" every complete take whatever its QC verdict."""
        if which not in TAKE_SELECTIONS:
            raise InputError("takes", f"expected one of {TAKE_SELECTIONS}, got {which!r}")
        complete = [t for t in self.manifest.takes if t.status in ("complete", "recovered")]
        if which == "all":
            return complete
        verdicts = self.qc_verdicts() if any(t.qc == "unchecked" for t in complete) else {}
        return [t for t in complete if (verdicts.get(t.name, "unchecked") if t.qc == "unchecked" else t.qc)
                == "accepted"]

    def unchecked_hint(self) -> str:
        """Why "accepted" may select nothing, for an error message: imported takes that qc has not judged yet."""
        waiting = [t.name for t in self.manifest.takes if t.status in ("complete", "recovered")
                   and t.qc == "unchecked" and t.name not in self.qc_verdicts()]
        return (f" ({len(waiting)} take(s) not checked yet: run `odsplat qc {self.root}` or `odsplat run`)"
                if waiting else "")

    def qc_verdicts(self) -> dict[str, str]:
        """The verdict the qc stage gave each take from its file (`derived/qc.json`), {} before it ran. A take
        recorded as unchecked (an imported one) is selected by this verdict; a recorded verdict stands."""
        path = self.paths.qc_json
        if not path.is_file():
            return {}
        doc = load_json(path, missing="no QC result")
        check(doc, path, kind=QC_KIND, schema_version=QC_SCHEMA, capture_id=self.id)
        out = {}
        for t in doc.get("takes") or []:
            if not (isinstance(t, dict) and isinstance(t.get("name"), str) and t.get("checked") in QC_VERDICTS):
                raise InputError(path, "takes: expected objects with a name and a checked verdict")
            out[t["name"]] = t["checked"]
        return out

    def next_take_name(self, view: int | None = None) -> str:
        stem = f"v{view:02d}" if view is not None else "take"
        existing = {p.name.split(".")[0] for p in self.takes_dir.iterdir()} if self.takes_dir.exists() else set()
        k = 0
        while f"{stem}_{k:03d}" in existing:
            k += 1
        return f"{stem}_{k:03d}"

    def new_take(
        self,
        name: str | None = None,
        *,
        view: int | None = None,
        frame_shape: Sequence[int] | None = None,
        dtype: Any = np.uint16,
        bit_depth: int | None = None,
        channels: Sequence[ChannelInfo] | None = None,
        fps: float | None = None,
        attrs: Mapping[str, Any] | None = None,
        daq_t0_s: float = 0.0,
    ) -> TakeWriter:
        """Start recording a take; the manifest lists it once `finalize()` succeeds."""
        name = check_name(name or self.next_take_name(view), f"{self.root}: take name")
        if name in self.take_names():
            raise OdsplatError(f"{self.root}: take {name!r} exists already; raw takes are written once")
        channels = self.manifest.channels if channels is None else channels
        all_attrs = {"view": -1 if view is None else view, "fps": np.nan if fps is None else fps,
                     "capture": self.manifest.name}
        all_attrs.update(attrs or {})
        return TakeWriter(
            self.takes_dir / f"{name}.h5",
            frame_shape=frame_shape,
            dtype=dtype,
            bit_depth=bit_depth,
            channels=channels,
            daq_sample_rate_hz=self.manifest.daq_sample_rate_hz,
            daq_t0_s=daq_t0_s,
            attrs=all_attrs,
            on_finalize=self._register,
        )

    def _register(self, record: TakeRecord) -> None:
        self.manifest.takes = [t for t in self.manifest.takes if t.name != record.name] + [record]
        self.save_manifest()

    def open_take(self, name: str) -> TakeReader:
        for t in self.manifest.takes:
            if t.name == name:
                return TakeReader(self.root / t.file)
        raise InputError(self.root, f"no take {name!r}; the capture has {self.take_names()}")

    def partial_takes(self) -> list[Path]:
        """Unfinished take files left by a writer that stopped before finalising."""
        return sorted(self.takes_dir.glob("*" + PARTIAL_SUFFIX)) if self.takes_dir.exists() else []

    def unlisted_takes(self) -> list[Path]:
        """Finalised take files the manifest does not list (a crash between rename and manifest write)."""
        listed = {t.file for t in self.manifest.takes}
        return [p for p in sorted(self.takes_dir.glob("*.h5")) if f"takes/{p.name}" not in listed]

    def recover(self) -> list[RecoveryReport]:
        """Recover every unfinished take and list finalised takes the manifest missed."""
        reports = []
        for partial in self.partial_takes():
            report = recover_partial(partial)
            reports.append(report)
        for path in self.unlisted_takes():
            with TakeReader(path) as reader:
                record = TakeRecord(
                    name=path.name[:-3],
                    file=f"takes/{path.name}",
                    view=reader.view,
                    status="recovered" if reader.recovered else "complete",
                    qc=reader.qc.status,
                    n_frames=reader.n_frames,
                    n_samples=reader.n_samples,
                    created_utc=str(reader.attrs.get("created_utc", "")),
                )
            self._register(record)
        return reports

    def copy_static(self, files: Sequence[Path]) -> None:
        self.static_dir.mkdir(exist_ok=True)
        for src in files:
            shutil.copy2(src, self.static_dir / Path(src).name)
