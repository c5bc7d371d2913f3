"""Magnify every view of a capture: stream each take's frames through a magnifier into
`derived/magnified/METHOD/NAME.h5` and a video to watch, `NAME.mp4`, views in parallel processes when cores
allow; each take's motion is checked against the method's bound (`limits.py`).

The input is the takes' frames on sync's common grid (`derived/sync/NAME.h5`) when sync has run, so every
view's magnified motion shares one timeline; otherwise the raw takes (flagged in the output).
"""
from __future__ import annotations

import inspect
import json
import logging
import math
import os
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Executor
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.checks import (
    BLUR_PX,
    CHUNK_FRAMES,
    FRACTION,
    MAGNIFICATION,
    MAX_WIDTH_PX,
    PLAYBACK_FPS,
    VIDEO_FREQUENCY_HZ,
    WORKERS,
    Range,
    check_choice,
    check_fields,
    check_number,
    maybe,
    shown,
)
from odsplat.spine.contract import check, describe
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.framefile import (
    MAGNIFIED_KIND,
    FrameFile,
    atomic_h5,
    begin_outputs,
    create_frames,
    discard_outputs,
    prune_outputs,
    to_stored,
)
from odsplat.spine.manifest import load_json, utc_now
from odsplat.spine.mp4 import Mp4Writer, display_range, to_8bit
from odsplat.spine.pool import process_pool
from odsplat.spine.store import Capture
from odsplat.sync import AlignedTake, load_sync

from .base import Magnifier, luma
from .eulerian import LinearMagnifier
from .filters import KINDS, check_band, make_filter
from .learned.magnifier import LearnedMagnifier
from .limits import check_limit, motion_px, sample_indices
from .phase import PhaseMagnifier
from .roi import motion_box

log = logging.getLogger(__name__)

METHODS = ("phase", "linear", "learned")
MODES = ("static", "dynamic")             # the learned method's without a band (learned.MODES): against the
#                                           first frame, or the one before
SOURCES = ("auto", "aligned", "raw")
ROIS = ("auto", "none")                   # where magnify works: the box of what moves, or the whole frame
MAX_VIEW = 9999                           # a viewpoint's number
KIND = "odsplat.magnify"
SCHEMA = 3   # 2: generation, the run id its magnified files carry; 3: each take's video and motion limit


@dataclass(frozen=True)
class MagnifySettings:
    method: str = "phase"                        # the magnification method: phase, linear or learned
    alpha: float = 20.0                          # output motion = alpha x input motion
    band_hz: tuple[float, float] | None = None   # temporal band; None: static mode (against the first frame)
    filter: str | None = None                    # default: butter with a band, none without
    mode: str = "static"                         # learned only: static or dynamic
    source: str = "auto"                         # aligned (sync's grid), raw (the takes), auto: aligned if synced
    chunk_frames: int = 16
    workers: int | None = None                   # default: one per core, at most one per take
    takes: tuple[str, ...] = ()                  # only these takes, all of them (default: every take sync kept,
    #                                              else every accepted take; of those, the first view's or `views`)
    views: tuple[int, ...] = ()                  # only these viewpoints' takes (of those above); default: the
    #                                              first view's, the one to watch (every_view: all of them)
    every_view: bool = False                     # every view's takes: what a reconstruction from magnified frames
    #                                              needs (`odsplat run` sets it then, unless views are named)
    options: tuple[tuple[str, Any], ...] = ()    # the method's own keyword arguments, e.g. (("n_orientations", 8),)
    video: bool = True                           # an 8-bit mp4 to watch beside each magnified take
    video_fps: float = 30.0                      # its playback rate (slow motion; the recorded rate is in its comment)
    side_by_side: bool = False                   # the video shows the input (left) beside the magnified (right)
    roi: str = "auto"                            # "auto": magnify only the box where the take moves above its
    #                                              noise, plus a margin (roi.py), the input frames elsewhere;
    #                                              "none": the whole frame

    def __post_init__(self) -> None:
        check_choice("MagnifySettings.method", self.method, METHODS)
        if self.filter is not None:
            check_choice("MagnifySettings.filter", self.filter, KINDS)
        if self.filter not in (None, "none") and self.band_hz is None:
            raise InputError("--band", f"the {self.filter} filter needs a band LOW HIGH in Hz")
        check_choice("MagnifySettings.mode", self.mode, MODES)
        check_choice("MagnifySettings.source", self.source, SOURCES)
        check_choice("MagnifySettings.roi", self.roi, ROIS)
        check_fields(self, {"alpha": MAGNIFICATION, "band_hz": maybe(VIDEO_FREQUENCY_HZ), "chunk_frames": CHUNK_FRAMES,
                            "workers": maybe(WORKERS), "video_fps": PLAYBACK_FPS,
                            "views": Range(at_least=0, at_most=MAX_VIEW, integer=True)})
        if self.band_hz is not None and not self.band_hz[0] < self.band_hz[1]:
            raise InputError("MagnifySettings.band_hz", f"expected LOW < HIGH in Hz, got {list(self.band_hz)}")
        check_options(self.method, self.options)

    @property
    def filter_kind(self) -> str:
        return self.filter or ("butter" if self.band_hz else "none")


def parse_options(items) -> tuple[tuple[str, Any], ...]:
    """A magnifier's keyword arguments from KEY=VALUE strings (`odsplat magnify --option`): VALUE is read as JSON
    (numbers, true/false in any case, lists), else kept as a string."""
    parsed = []
    for item in items:
        key, eq, value = str(item).partition("=")
        if not eq or not key.isidentifier():
            raise InputError("--option", f"expected KEY=VALUE, got {item!r}")
        try:
            parsed.append((key, json.loads(value.lower() if value.lower() in ("true", "false") else value)))
        except (ValueError, RecursionError):  # not JSON (or nested past reading): kept as a string
            parsed.append((key, value))
    return tuple(parsed)


def _magnifier_class(method: str) -> type[Magnifier]:
    if method == "phase":

        return PhaseMagnifier
    if method == "linear":

        return LinearMagnifier

    return LearnedMagnifier


_OPTION_TYPES = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}
# The numeric options' ranges: past any real use, short of sizes that allocate without bound.
_OPTION_RANGES = {
    "n_orientations": Range(at_least=1, at_most=16, integer=True),
    "n_scales": maybe(Range(at_least=1, at_most=16, integer=True)),
    "levels": Range(at_least=0, at_most=16, integer=True),
    "sigma_px": BLUR_PX,
    "twidth": Range(above=0, at_most=4),                  # octaves
    "noise_sd": maybe(FRACTION),
    "cutoff_wavelength_px": Range(above=0, at_most=MAX_WIDTH_PX),
    "batch_frames": CHUNK_FRAMES,
    "batch": CHUNK_FRAMES,
}


def check_options(method: str, options: tuple[tuple[str, Any], ...]) -> None:
    """Each option must be a keyword of the method's magnifier, of the type it declares (a finite number where it
    takes one), so that a bad one is refused by name before any frame is read."""
    if not options:
        return
    params = {n: p for n, p in inspect.signature(_magnifier_class(method).__init__).parameters.items()
              if p.kind is inspect.Parameter.KEYWORD_ONLY and n != "mode"}
    for key, value in options:
        where = f"MagnifySettings.options.{key}"
        if key not in params:
            raise InputError(where, f"the {method} method has no such option; it has {', '.join(params)}")
        names = {t.strip() for t in str(params[key].annotation).split("|")}
        if value is None and "None" in names:
            continue
        kinds = tuple(t for n in names for t in _OPTION_TYPES.get(n, ()))
        fits = "bool" in names if isinstance(value, bool) else isinstance(value, kinds)
        if not fits or (isinstance(value, float) and not math.isfinite(value)):
            raise InputError(where, f"expected {' or '.join(sorted(names))} for the {method} method; got "
                                    f"{shown(value)}")
        if key in _OPTION_RANGES and not isinstance(value, bool):
            check_number(where, value, _OPTION_RANGES[key])


def make_magnifier(settings: MagnifySettings, fps: float) -> Magnifier:
    """A fresh magnifier for one stream, with its own temporal filter."""
    s = settings
    temporal = None
    if s.filter_kind != "none":
        lo, hi = s.band_hz
        check_band(lo, hi, fps)
        temporal = make_filter(s.filter_kind, fps, lo, hi)
    options = dict(s.options)
    try:
        if s.method == "phase":

            return PhaseMagnifier(s.alpha, temporal, **options)
        if s.method == "linear":

            return LinearMagnifier(s.alpha, temporal, **options)

        return LearnedMagnifier(s.alpha, temporal, mode=s.mode, **options)
    except TypeError as e:  # an option the method does not have
        raise InputError("--option", f"{s.method}: {e}") from None


@dataclass
class MagnifiedTake:
    name: str
    view: int | None
    source: str
    n_frames: int
    file: str
    seconds: float
    video: dict[str, Any] | None = None    # the mp4: file, fps (playback), recorded_fps, dn_range, codec, bytes, ...
    limit: dict[str, Any] | None = None    # the motion against the method's bound (limits.MotionLimit)
    warning: str | None = None             # the limit's line, when alpha x motion passes it
    roi_px: list[int] | None = None        # the box magnified, [y0, y1, x0, x1] (None: the whole frame)


@dataclass
class MagnifyResult:
    method: str
    alpha: float
    band_hz: list[float] | None
    filter: str
    takes: list[MagnifiedTake] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    created_utc: str = field(default_factory=utc_now)
    generation: str = ""              # the run's id; every magnified file it wrote carries it

    def write(self, capture: Capture) -> Path:
        """magnify.json beside the magnified takes (written after them)."""
        path = capture.paths.magnify_json(self.method)
        header = describe(capture.id, KIND, SCHEMA, self.settings).header()
        atomic_write_text(path, json.dumps({**header, **asdict(self)}, indent=1))
        return path

    @classmethod
    def read(cls, capture: Capture, method: str) -> MagnifyResult:
        path = capture.paths.magnify_json(method)
        d = load_json(path, missing=f"no {method} magnification here (run `odsplat magnify --method {method}`)")
        check(d, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
        try:
            takes = [MagnifiedTake(**t) for t in d["takes"]]
            return cls(d["method"], d["alpha"], d["band_hz"], d["filter"], takes, d["settings"], d["created_utc"],
                       d["generation"])
        except (TypeError, KeyError) as exc:
            raise InputError(path, f"not a readable magnification summary: {exc}") from None

    def summary(self) -> str:
        band = f", band {self.band_hz[0]:g}-{self.band_hz[1]:g} Hz ({self.filter})" if self.band_hz else ", static"
        lines = [f"{len(self.takes)} view(s) magnified by {self.alpha:g} with {self.method}{band}"]
        for t in self.takes:
            video = f" and {Path(t.video['file']).name}" if t.video else ""
            box = f" (magnified in the box of what moves, rows {t.roi_px[0]}-{t.roi_px[1] - 1}, columns " \
                  f"{t.roi_px[2]}-{t.roi_px[3] - 1})" if t.roi_px else ""
            lines.append(f"  {t.name:<10} {t.n_frames} frames from {t.source} in {t.seconds:.1f} s -> {t.file}{video}"
                         f"{box}")
        if self.takes and self.takes[0].video:
            v = self.takes[0].video
            lines.append(f"  videos play at {v['fps']:g} frames/s (recorded at {v['recorded_fps']:g}: "
                         f"{v['recorded_fps'] / v['fps']:.3g}x slower)")
        lines += [f"  warning: {t.warning}" for t in self.takes if t.warning]
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------- one take

class _Source:
    """Frames of one take as DN float32 chunks (T, H, W[, C]), from sync's grid or the raw take."""

    def __init__(self, capture: Capture, name: str, aligned_file: str | None, sync_generation: str | None = None):
        self.name = name
        if aligned_file:

            self._r = AlignedTake(capture, Path(aligned_file), sync_generation)
            self.kind = "aligned"
            self.bit_depth = int(self._r.attrs["bit_depth"])
            self.times_s = self._r.times_s
            self.fps = float(1.0 / np.median(np.diff(self.times_s))) if len(self.times_s) > 1 else None
            self.view = self._r.attrs.get("view")
        else:
            self._r = capture.open_take(name)
            self.kind = "raw"
            self.bit_depth = self._r.bit_depth
            self.times_s = self._r.frame_times_s
            self.fps = self._r.fps
            self.view = self._r.view
        self.n_frames = self._r.n_frames
        self.frame_shape = tuple(self._r.frame_shape)

    def chunks(self, n: int) -> Iterator[np.ndarray]:
        for block in self._r.iter_frames(n):
            yield np.asarray(block, np.float32)

    def close(self) -> None:
        self._r.close()


def _to_tensor(block: np.ndarray, full_scale: float) -> torch.Tensor:
    x = torch.from_numpy(block / full_scale)
    return x[:, None] if x.ndim == 3 else x.permute(0, 3, 1, 2)


def _from_tensor(x: torch.Tensor, full_scale: float, rgb: bool) -> np.ndarray:
    a = x.detach().cpu().numpy()
    a = a[:, 0] if not rgb else a.transpose(0, 2, 3, 1)
    return a * full_scale


def video_comment(take: str, what: str, recorded_fps: float, fps: float, dn_range: tuple[float, float]) -> str:
    """The mp4's comment: what it shows, its real frame rate and its 8-bit mapping."""
    return (f"odsplat: {take}, {what}; recorded at {recorded_fps:g} frames/s, played at {fps:g} frames/s "
            f"({recorded_fps / fps:.4g}x slower); 8-bit from {dn_range[0]:g} to {dn_range[1]:g} DN")


def magnify_take(capture_root: str, name: str, aligned_file: str | None, settings: MagnifySettings,
                 out_path: str, threads: int = 1, derived_root: str | None = None, generation: str = "",
                 sync_generation: str | None = None, video_path: str | None = None) -> MagnifiedTake:
    """Stream one take (`aligned_file`: the path of its aligned frames, of sync's run `sync_generation`, or None
    for the raw take) through a fresh magnifier into out_path (temporary file, fsync, rename), marked as this
    run's (`generation`), and into an 8-bit mp4 at `video_path` (None: none). The take's motion is measured on
    its input frames against the method's bound."""
    torch.set_num_threads(threads)
    t0 = time.perf_counter()
    capture = Capture.open(capture_root, derived=derived_root)
    src = _Source(capture, name, aligned_file, sync_generation)
    try:
        if not src.fps:
            raise InputError(name, "the take has no frame rate: a temporal band cannot be placed")
        mag = make_magnifier(settings, src.fps)
        full = float(2 ** src.bit_depth - 1)
        rgb = len(src.frame_shape) == 3
        out = Path(out_path)
        written = 0
        dn_range: tuple[float, float] | None = None
        samples = set(sample_indices(src.n_frames).tolist())
        reference, sampled, read = None, [], 0
        held: deque[np.ndarray] = deque()   # side by side: input frames waiting for their magnified frames
        writer = Mp4Writer(video_path, settings.video_fps) if video_path else None
        box = motion_box(src.chunks(settings.chunk_frames), src.times_s, src.frame_shape) \
            if settings.roi == "auto" else None
        inputs: deque[np.ndarray] = deque()   # with a box: the input frames the magnified box goes into
        with atomic_h5(out) as f:
            attrs = dict(take=name, source=src.kind, method=settings.method, alpha=settings.alpha,
                         filter=settings.filter_kind, mode=settings.mode,
                         band_hz=json.dumps(list(settings.band_hz) if settings.band_hz else None),
                         view=None if src.view is None else int(src.view), generation=generation)
            ds, scale = create_frames(f, MAGNIFIED_KIND, frame_shape=src.frame_shape, bit_depth=src.bit_depth,
                                      times_s=src.times_s, attrs=attrs, capture_id=capture.id)

            def emit(y: torch.Tensor) -> None:
                nonlocal written
                if y.shape[0] == 0:
                    return
                dn = _from_tensor(y, full, rgb)
                if box is not None:
                    frames = np.stack([inputs.popleft() for _ in range(len(dn))])
                    frames[(slice(None), *box.slices)] = dn
                    dn = frames
                ds.resize(written + len(y), axis=0)
                ds[written:written + len(y)] = to_stored(dn, scale)
                written += len(y)
                if writer is not None:
                    for frame in to_8bit(dn, dn_range):
                        writer.write(np.concatenate([held.popleft(), frame], axis=1) if settings.side_by_side
                                     else frame)

            try:
                for block in src.chunks(settings.chunk_frames):
                    if dn_range is None:
                        dn_range = display_range(block)
                    if settings.side_by_side and writer is not None:
                        held.extend(to_8bit(block, dn_range))
                    y8 = to_8bit(luma(block), dn_range)
                    reference = y8[0] if reference is None else reference
                    sampled += [y8[i - read] for i in range(read, read + len(block)) if i in samples]
                    read += len(block)
                    if box is not None:
                        inputs.extend(block)
                        block = np.ascontiguousarray(block[(slice(None), *box.slices)])
                    emit(mag.push(_to_tensor(block, full)))
                emit(mag.flush())
                if written != src.n_frames:
                    raise OdsplatError(f"{name}: the magnifier returned {written} frames for {src.n_frames}")
                video = None
                if writer is not None:
                    what = (f"magnified x{settings.alpha:g} ({settings.method}"
                            + (f", {settings.band_hz[0]:g}-{settings.band_hz[1]:g} Hz" if settings.band_hz else
                               ", static") + ")" + ("; left: input, right: magnified" if settings.side_by_side else ""))
                    writer.comment = video_comment(name, what, src.fps, settings.video_fps, dn_range)
                    info = writer.close()
                    video = dict(file=os.path.relpath(info.path, capture.paths.root), fps=info.fps,
                                 recorded_fps=src.fps, dn_range=list(dn_range), codec=info.codec, bytes=info.bytes,
                                 width_px=info.width_px, height_px=info.height_px, side_by_side=settings.side_by_side,
                                 comment=info.comment)
            except BaseException:
                if writer is not None:
                    writer.abort()
                raise
    finally:
        src.close()
    limit = check_limit(settings.method, settings.alpha, motion_px(reference, sampled), dict(settings.options),
                        list(settings.band_hz) if settings.band_hz else None)
    return MagnifiedTake(name, None if src.view is None else int(src.view), src.kind, written,
                         os.path.relpath(out, capture.paths.root), time.perf_counter() - t0, video, asdict(limit),
                         limit.line(name) if limit.passes else None, None if box is None else box.as_list())


# ---------------------------------------------------------------------------------------------- a capture

def _inputs(capture: Capture, s: MagnifySettings) -> tuple[list[tuple[str, str | None]], str | None]:
    """(take, aligned file or None) for each take to magnify, and the generation of sync's run (None: raw)."""
    synced = None
    sync_json = capture.paths.sync_json
    if s.source in ("auto", "aligned") and sync_json.exists():

        sync = load_sync(capture)
        synced = {t.name: str(capture.paths.listed(t.aligned_file)) for t in sync.ok if t.aligned_file}
    if s.source == "aligned" and not synced:
        raise InputError(sync_json, "no aligned frames: run `odsplat sync` first (or --source raw)")
    if synced:
        names = list(s.takes) or list(synced)
        missing = [n for n in names if n not in synced]
        if missing:
            raise InputError(sync_json, f"takes {missing} are not on sync's grid (excluded or not synced)")
        return [(n, synced[n]) for n in _of_views(capture, names, s)], sync.generation
    names = list(s.takes) or [t.name for t in capture.select_takes("accepted") if t.n_frames > 0]
    known = set(capture.take_names())
    missing = [n for n in names if n not in known]
    if missing:
        raise InputError(capture.root, f"no takes named {missing}")
    return [(n, None) for n in _of_views(capture, names, s)], None


def _of_views(capture: Capture, names: list[str], s: MagnifySettings) -> list[str]:
    """The takes of `names` filmed from one of `s.views`; without views, every take (s.every_view, or s.takes
    named) or the first view's (the lowest view number; the first take where the takes have none): a magnified view
    is for someone to watch, and at the seed's scale (27 views x 640 frames x 1024^2) magnifying them all took most
    of the run (issue 44). None is an error."""
    views = s.views
    view_of = {t.name: t.view for t in capture.manifest.takes}
    if not views:
        if s.every_view or s.takes or not names:
            return names
        numbered = [view_of.get(n) for n in names if view_of.get(n) is not None]
        if not numbered:
            return names[:1]
        first = min(numbered)
        return [n for n in names if view_of.get(n) == first]
    wanted = set(views)
    kept = [n for n in names if view_of.get(n) in wanted]
    if not kept:
        raise InputError("magnify.views", f"no take to magnify from views {list(views)} "
                         f"(the takes' views: {sorted({v for v in view_of.values() if v is not None})})")
    return kept


def magnify_capture(capture: Capture, settings: MagnifySettings, *, progress: bool = True,
                    executor: Executor | None = None) -> MagnifyResult:
    """Magnify every selected view; writes derived/magnified/METHOD/NAME.h5 (and NAME.mp4 unless `video` is off)
    and magnify.json beside them; warns for the takes whose magnified motion passes the method's bound.

    Each view is its own task, in a process pool of `settings.workers`, or through `executor.map` when one is
    given (e.g. a Dask client's executor: the views of one capture spread over a cluster, one thread each);
    each writes only its own files, and the index is written here once they are all done."""
    s = settings
    jobs, sync_generation = _inputs(capture, s)
    if not jobs:
        raise OdsplatError(f"{capture.root}: no takes to magnify{capture.unchecked_hint()}")
    dest = capture.paths.magnified_dir(s.method)
    sources = [Path(src) if src else capture.root / f"takes/{name}.h5" for name, src in jobs]
    generation = begin_outputs(capture.paths.magnify_json(s.method), dest, sources, "the magnified frames")
    capture.paths.ensure(dest)
    workers = max(1, min(s.workers or os.cpu_count() or 1, len(jobs)))
    # torch's threads per view: one per task on an executor (a cluster's worker slot), like the process pool when
    # the views outnumber the cores. With more, the frames are not reproducible to the last stored quarter DN
    threads = 1 if executor is not None else max(1, (os.cpu_count() or 1) // workers)
    result = MagnifyResult(s.method, s.alpha, list(s.band_hz) if s.band_hz else None, s.filter_kind,
                           settings=asdict(s), generation=generation)
    args = [(str(capture.root), n, a, s, str(capture.paths.magnified(s.method, n)), threads, str(capture.paths.root),
             generation, sync_generation, str(capture.paths.magnified_video(s.method, n)) if s.video else None)
            for n, a in jobs]
    bar = tqdm(total=len(args), desc=f"magnify ({s.method})", unit="view", disable=not progress)
    try:
        if workers == 1 and executor is None:
            for a in args:
                result.takes.append(magnify_take(*a))
                bar.update()
        else:
            with nullcontext(executor) if executor is not None else process_pool(workers) as pool:
                for done in pool.map(magnify_take, *zip(*args)):
                    result.takes.append(done)
                    bar.update()
    except BaseException:
        discard_outputs(dest)   # no index lists them
        raise
    finally:
        bar.close()
    result.write(capture)
    prune_outputs(dest, [capture.paths.listed(f) for t in result.takes
                         for f in (t.file, *([t.video["file"]] if t.video else []))])
    warned = [t for t in result.takes if t.warning]
    if len(warned) <= 3:
        for t in warned:
            log.warning("%s", t.warning)
    else:   # one line for the run; each take's in magnify.json and the stage's summary
        fits = [t.limit.get("fits_alpha") for t in warned if t.limit and t.limit.get("fits_alpha") is not None]
        log.warning("%d of %d takes: alpha %g x their motion passes the %s method's limit%s (each take's line in %s)",
                    len(warned), len(result.takes), s.alpha, s.method,
                    f"; alpha <= {min(fits):.3g} fits them all" if fits else "", capture.paths.magnify_json(s.method))
    log.info("magnified %d view(s) into %s", len(result.takes), dest)
    return result


class MagnifiedVideo(FrameFile):
    """Reads a magnified take: frames as float32 DN of the source take, with their times."""

    KIND = MAGNIFIED_KIND
    WHAT = "magnified take"
    MISSING = "no such magnified take (run `odsplat magnify` first)"


__all__ = ["METHODS", "MagnifiedTake", "MagnifiedVideo", "MagnifyResult", "MagnifySettings", "magnify_capture",
           "magnify_take", "make_magnifier"]
