"""Writing a take file: `TakeWriter` records one take crash-safely into `<name>.h5.partial` (SWMR, flushed per frame
and per block) and finalises it as `<name>.h5`; `TriggerInfo` and `QCInfo` are what it records beside the data.
The layout it writes is in take_reader.py and docs/store.md."""
from __future__ import annotations

import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from odsplat.spine.atomic import frame_compression, fsync_path
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.manifest import CAN_SOURCE_PREFIX, SCHEMA_VERSION, ChannelInfo, TakeRecord, utc_now
from odsplat.spine.space import CHUNK_CACHE_BYTES, Reserve, close_h5, writing_h5

log = logging.getLogger(__name__)

PARTIAL_SUFFIX = ".h5.partial"
_FRAME_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16))


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
            self._create_frames(f)
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

    def _create_frames(self, f: h5py.File) -> None:
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
            view=view_or_none(self._view),
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


# HDF5 attributes cannot be None: a take file stores an unknown number as NaN, and "no viewpoint" as -1. Both
# directions live here, beside the writer that encodes them; take_reader.py decodes with them, as does `finalize`.


def _none_to_nan(value: Any) -> Any:
    return np.nan if value is None else value


def nan_to_none(value: Any) -> Any:
    if value is None:
        return None
    if isinstance(value, (float, np.floating)) and np.isnan(value):
        return None
    return value.item() if isinstance(value, np.generic) else value


def maybe_int(value: Any) -> int | None:
    value = nan_to_none(value)
    return None if value is None or value == "" else int(value)


def view_or_none(value: Any) -> int | None:
    """A take file stores "no viewpoint" as -1 (HDF5 attributes cannot be None)."""
    view = maybe_int(value)
    return None if view is None or view < 0 else view
