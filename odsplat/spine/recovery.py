"""Crash recovery: an unfinished take (`<name>.h5.partial`, left by a writer that stopped) becomes a finalised take
marked `recovered` that holds every frame and sample flushed, read through the take reader's layout parser."""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from odsplat.spine.atomic import fsync_path
from odsplat.spine.errors import storage_error
from odsplat.spine.manifest import check_schema
from odsplat.spine.take_reader import TakeLayout
from odsplat.spine.take_writer import PARTIAL_SUFFIX, QCInfo, TakeWriter

log = logging.getLogger(__name__)

CRASHED_SUFFIX = ".h5.crashed"


@dataclass(frozen=True)
class RecoveryReport:
    """What `recover_partial` did with one unfinished take file."""

    name: str
    recovered: bool
    n_frames: int
    n_samples: int
    message: str
    path: Path | None = None


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
            layout = TakeLayout(src, partial_path)
            has_frames = layout.has_frames
            # What was flushed, as the writer orders its writes: the shortest of a frame's datasets, of the DAQ
            # channels, and of a CAN node's values and times.
            n_frames = (min(src["frames"].shape[0], src["frame_counter"].shape[0], src["frame_times_s"].shape[0])
                        if has_frames else 0)
            daq = src["daq"]
            names = layout.channel_names
            n_samples = min((daq[n].shape[0] for n in names), default=0)
            channels = [layout.channel_info(n) for n in names]
            can = {}  # node -> (its channel names, samples whose values and times were both flushed)
            for node in layout.can_nodes:
                g = src["can"][node]
                node_names = layout.can_node_channels(node)
                channels += [layout.channel_info(n) for n in node_names]
                can[node] = (node_names, min(g[n].shape[0] for n in ["times_s", *node_names]))
            attrs = {k: v for k, v in src.attrs.items() if k not in ("odsplat_schema", "kind", "complete", "recovered")}
            for leftover in half_made:
                leftover.unlink(missing_ok=True)
            writer = TakeWriter(
                tmp_final,
                frame_shape=layout.frame_shape if has_frames else None,
                dtype=layout.frames.dtype if has_frames else np.uint16,
                bit_depth=layout.bit_depth if has_frames else None,
                channels=channels,
                daq_sample_rate_hz=layout.sample_rate_hz or None,
                daq_t0_s=layout.daq_t0_s,
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
