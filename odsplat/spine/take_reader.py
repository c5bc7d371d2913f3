"""Reading a take file: the one parser of its layout (`TakeLayout`), and `TakeReader`, which reads a finalised take
through every raw dataset's checksums (`CheckedDataset`). Layout (schema 1.x; docs/store.md)::

    /frames               (T,H,W) or (T,H,W,3) uint8|uint16, one frame per chunk, Blosc-zstd + bitshuffle
    /frame_times_s        (T,) float64, frame exposure starts in the DAQ time base (NaN when unknown)
    /frame_counter        (T,) int64, the camera's own frame number (gaps reveal dropped frames)
    /daq/<channel>        (N,) float32 in SI units, attrs unit, kind
    /can/<node>/times_s   (M,) float64, each CAN sample's time in the DAQ time base (schema 1.1)
    /can/<node>/<channel> (M,) float32 in SI units at the node's own rate, NaN where a sample was lost
    /trigger, /qc         attributes, written when the take is finalised
"""
from __future__ import annotations

import functools
import json
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from odsplat.spine.errors import IncompleteTakeError, InputError, SchemaError
from odsplat.spine.manifest import ChannelInfo, check_name, check_schema
from odsplat.spine.take_writer import PARTIAL_SUFFIX, QCInfo, TriggerInfo, maybe_int, nan_to_none, view_or_none
from odsplat.spine.timebase import resample_onto

log = logging.getLogger(__name__)


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


class TakeLayout:
    """The layout of a take file read from an open HDF5 file, finalised or still unfinished: its frames, its DAQ
    channels, its CAN nodes and each channel's manifest entry. The one parser of the layout: `TakeReader` reads a
    finalised take through it, and `recovery.recover_partial` an unfinished one."""

    def __init__(self, file: h5py.File, path: Path):
        self._file = file
        self.path = path

    # -- frames -----------------------------------------------------------------------------

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
    def frame_shape(self) -> tuple[int, ...]:
        return tuple(self.frames.shape[1:])

    @property
    def bit_depth(self) -> int:
        return int(self.frames.attrs["bit_depth"])

    # -- DAQ channels -----------------------------------------------------------------------

    @property
    def sample_rate_hz(self) -> float:
        return float(self._file["daq"].attrs["sample_rate_hz"])

    @property
    def daq_t0_s(self) -> float:
        return float(self._file["daq"].attrs["t0_s"])

    @property
    def channel_names(self) -> list[str]:
        return json.loads(self._file["daq"].attrs["channel_order"])

    def channel_info(self, name: str) -> ChannelInfo:
        """A DAQ or CAN channel's manifest entry, as recorded in the take."""
        ds = self._file["can"][self._can_node_of(name)][name] if name in self._can_index else self._channel(name)
        return ChannelInfo(**json.loads(ds.attrs["info"]))

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

    def can_node_channels(self, node: str) -> list[str]:
        """A CAN node's channels, in order."""
        return json.loads(self._can_group(node).attrs["channel_order"])

    @functools.cached_property
    def _can_index(self) -> dict[str, str]:
        """CAN channel name -> its node."""
        return {name: node for node in self.can_nodes for name in self.can_node_channels(node)}

    def _can_node_of(self, name: str) -> str:
        try:
            return self._can_index[name]
        except KeyError:
            raise InputError(self.path, f"no CAN channel {name!r}; the take has {self.can_channel_names}") from None

    def _can_group(self, node: str) -> h5py.Group:
        if node not in self.can_nodes:
            raise InputError(self.path, f"no CAN node {node!r}; the take has {self.can_nodes}")
        return self._file["can"][node]


class TakeReader(TakeLayout):
    """Reads a finalised take file; frames are streamed in chunks, never loaded whole. Every read of a raw dataset
    goes through its checksums (`CheckedDataset`)."""

    def __init__(self, path: str | Path):
        path = Path(path)
        if path.name.endswith(PARTIAL_SUFFIX):
            raise IncompleteTakeError(path, "this take was never finalised; run `odsplat recover` on its capture")
        try:
            file = h5py.File(path, "r")
        except FileNotFoundError:
            raise InputError(path, "no such take file") from None
        except OSError as exc:
            raise InputError(path, f"cannot be opened as HDF5 ({exc})") from None
        super().__init__(file, path)
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
        return {k: nan_to_none(v) for k, v in self._file.attrs.items()}

    @property
    def view(self) -> int | None:
        return view_or_none(self._file.attrs.get("view"))

    @property
    def n_frames(self) -> int:
        return self.frames.shape[0] if self.has_frames else 0

    @property
    def fps(self) -> float | None:
        return nan_to_none(self._file.attrs.get("fps"))

    @property
    def frame_times_s(self) -> np.ndarray:
        return self.dataset("frame_times_s")[:] if self.has_frames else np.empty(0)

    @property
    def frame_counter(self) -> np.ndarray:
        return self.dataset("frame_counter")[:] if self.has_frames else np.empty(0, dtype="i8")

    @property
    def n_samples(self) -> int:
        names = self.channel_names
        return self._file["daq"][names[0]].shape[0] if names else 0

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

    # -- CAN nodes (schema 1.1) ---------------------------------------------------------------

    def can_times_s(self, node: str) -> np.ndarray:
        """The node's sample times in the DAQ time base (float64)."""
        self._can_group(node)
        return self.dataset(f"can/{node}/times_s")[:]

    def can_channel(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """A CAN channel's own samples: (times in the DAQ time base, float64; values in SI units, float32, NaN
        where a sample was lost)."""
        node = self._can_node_of(name)
        return self.dataset(f"can/{node}/times_s")[:], self.dataset(f"can/{node}/{name}")[:]

    # -- trigger, QC and file -------------------------------------------------------------------

    @property
    def trigger(self) -> TriggerInfo:
        a = self._file["trigger"].attrs
        return TriggerInfo(
            trigger_sample=maybe_int(a.get("trigger_sample")),
            pretrigger_samples=maybe_int(a.get("pretrigger_samples")),
            camera_trigger_frame=maybe_int(a.get("camera_trigger_frame")),
            trigger_time_s=nan_to_none(a.get("trigger_time_s")),
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
