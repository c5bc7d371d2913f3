"""The pipeline: the stage graph from raw takes to the report, each stage run through its one entry, skipped
when its outputs are current and rerun, with everything downstream, when they are stale.

A stage is current when its stamp, `derived/pipeline/STAGE.json`, records the fingerprint the stage would have
now (a hash of its settings, the capture and its inputs' identities: the raw takes for the first stages, the
run id of each upstream stage's last run for the others) and its output files are as the stamp lists them: the
same files, each of the same size and content digest (`output_identity`), so an edit that keeps a file's size and
modification time still makes the stage stale.
The stamp is removed before a stage runs and written, atomically, after its outputs: a stage killed at any
point leaves no stamp, and the next run does it again. Every run of a stage gets a new run id, so a rerun
upstream makes the stages downstream stale.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from odsplat.app.budget import Budget, within_budget
from odsplat.app.config import Config, load_config
from odsplat.app.stages import BY_NAME, STAGES, TABLE, Stage, stage
from odsplat.app.stages import walk as _walk
from odsplat.spine.atomic import atomic_write_text, fsync_path, remove_stale_temporaries
from odsplat.spine.contract import Provenance, check, describe, digest, plain
from odsplat.spine.errors import InputError, OdsplatError, one_line, storage_error
from odsplat.spine.lock import capture_lock
from odsplat.spine.manifest import load_json
from odsplat.spine.sensors import geometry_identity
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

STAMP_KIND = "odsplat.stage"
STAMP_SCHEMA = 2   # 2: each output's content digest instead of its modification time (older stamps read as stale)
DIGEST = "sha256"   # the outputs' content digest (hashlib) over each file's bytes; with the CPU's SHA instructions
#                     twice blake2b's speed (1.5 against 0.8 GB/s on our 2-core machines)
_BLOCK = 1 << 20    # bytes read at a time while digesting


# ------------------------------------------------------------------------------------------ the stage graph

# The graph is the stage table (odsplat/app/stages.py: each stage's settings, entry, inputs and outputs).
GRAPH: tuple[Stage, ...] = TABLE


# ------------------------------------------------------------------------------------------ identities

def file_digest(path: Path) -> str:
    """The content digest of one file (`DIGEST`), streamed in blocks of `_BLOCK` bytes."""
    h = hashlib.new(DIGEST)
    with open(path, "rb") as fh:
        while block := fh.read(_BLOCK):
            h.update(block)
    return f"{DIGEST}:{h.hexdigest()}"


def _output_files(capture: Capture, paths: Iterable[Path]) -> dict[str, tuple[Path, int]]:
    """Every output file (folders walked), by its path under the derived folder, with its size."""
    out = {}
    for p in paths:
        for f in _walk(p):
            try:
                size = f.stat().st_size
            except FileNotFoundError:
                continue
            out[os.path.relpath(f, capture.paths.root)] = (f, size)
    return out


def output_identity(capture: Capture, paths: Iterable[Path]) -> dict[str, list]:
    """Every output file (folders walked) with its size and content digest (`file_digest`): what the stamp
    vouches for. Content, not the modification time: an edit that keeps the size and puts the time back is
    seen too."""
    return _identity(_output_files(capture, paths))


def _identity(files: dict[str, tuple[Path, int]]) -> dict[str, list]:
    out = {}
    for rel, (f, size) in files.items():
        try:
            out[rel] = [size, file_digest(f)]
        except FileNotFoundError:
            continue
    return out


def outputs_unchanged(capture: Capture, paths: Iterable[Path], recorded: dict[str, Any]) -> bool:
    """Whether the output files are those `recorded` (a stamp's `output_identity`): the same names and sizes
    first, which costs no reading, then each file's content digest."""
    files = _output_files(capture, paths)
    if set(files) != set(recorded):
        return False
    for rel, (_, size) in files.items():
        entry = recorded[rel]
        if not isinstance(entry, list) or entry[:1] != [size]:
            return False
    return _identity(files) == recorded


def takes_identity(capture: Capture) -> str:
    """The raw takes as the manifest lists them (name, file, status, QC, size) and the static photos."""
    takes = [[t.name, t.file, t.status, t.qc, t.n_frames, t.n_samples, t.created_utc] for t in capture.manifest.takes]
    photos = sorted(p for p in capture.static_dir.glob("*") if p.is_file()) if capture.static_dir.is_dir() else []
    static = [[p.name, (st := p.stat()).st_size, st.st_mtime_ns] for p in photos]
    return digest([takes, static])


def stage_settings(name: str, settings: Any) -> dict[str, Any]:
    """A stage's settings as recorded and hashed: its volatile ones left out (a dotted name: a nested one)."""
    d = plain(settings) if settings is not None else {}
    for key in stage(name).volatile:
        *outer, last = key.split(".")
        inner = d
        for part in outer:
            inner = inner.get(part) if isinstance(inner, dict) else None
        if isinstance(inner, dict):
            inner.pop(last, None)
    return d


@dataclass(frozen=True)
class Stamp:
    """A stage's last complete run: its provenance and the outputs it left."""

    provenance: Provenance
    outputs: dict[str, list[int]]
    seconds: float
    summary: str

    @classmethod
    def read(cls, capture: Capture, name: str) -> Stamp | None:
        """The stage's stamp; None when it has none, or one an older odsplat wrote (stale: the stage runs
        again). A stamp that is damaged, another capture's or a newer odsplat's is refused with one line."""
        path = capture.paths.stamp(name)
        if not path.exists():
            return None
        doc = load_json(path, missing="no stamp")
        if _older_stamp(doc):
            return None
        prov = check(doc, path, kind=STAMP_KIND, schema_version=STAMP_SCHEMA, capture_id=capture.id)
        if doc.get("stage") != name or not isinstance(doc.get("outputs"), dict):
            raise InputError(path, f"not the stamp of stage {name!r}")
        return cls(prov, doc["outputs"], float(doc.get("seconds", 0.0)), str(doc.get("summary", "")))

    def write(self, capture: Capture, name: str) -> None:
        path = capture.paths.stamp(name)
        capture.paths.ensure(path.parent)
        doc = {**self.provenance.header(), "stage": name, "outputs": self.outputs, "seconds": self.seconds,
               "summary": self.summary}
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")


def _older_stamp(doc: Any) -> bool:
    """A stamp of an older schema (its outputs identified another way): read as no stamp, so the stage reruns."""
    version = doc.get("schema_version") if isinstance(doc, dict) and doc.get("kind") == STAMP_KIND else None
    return isinstance(version, int) and not isinstance(version, bool) and version < STAMP_SCHEMA


def _inputs(capture: Capture, name: str, config: Config) -> dict[str, str]:
    st = stage(name)
    inputs = {"takes": takes_identity(capture)} if st.raw else {}
    if st.geometry:
        inputs["geometry"] = geometry_identity(capture)
    for up in st.upstream(config):
        stamp = Stamp.read(capture, up)
        inputs[up] = stamp.provenance.run_id if stamp else "missing"
    return inputs


def expected(capture: Capture, name: str, config: Config) -> Provenance:
    """The provenance a run of stage `name` would record now."""
    return describe(capture.id, STAMP_KIND, STAMP_SCHEMA, stage_settings(name, config.settings(name)),
                    _inputs(capture, name, config))


def is_current(capture: Capture, name: str, config: Config) -> tuple[bool, str]:
    """Whether the stage's outputs are current, and if not, why (one phrase)."""
    return _currency(capture, name, config)[:2]


def _currency(capture: Capture, name: str, config: Config) -> tuple[bool, str, Stamp | None]:
    """`is_current` with the stamp it read."""
    stamp = Stamp.read(capture, name)
    if stamp is None:
        older = capture.paths.stamp(name).exists()
        return False, "stamped by an older odsplat" if older else "not run yet", None
    want = expected(capture, name, config)
    if stamp.provenance.fingerprint != want.fingerprint:
        old = stamp.provenance
        if old.settings != want.settings:
            changed = sorted(k for k in set(old.settings) | set(want.settings)
                             if old.settings.get(k) != want.settings.get(k))
            return False, f"settings changed ({', '.join(changed)})", stamp
        changed = sorted(k for k in set(old.inputs) | set(want.inputs) if old.inputs.get(k) != want.inputs.get(k))
        return False, f"inputs changed ({', '.join(changed)})", stamp
    st = stage(name)
    if not outputs_unchanged(capture, st.outputs(capture, config.settings(name)), stamp.outputs):
        return False, "its outputs changed on disk", stamp
    return True, "current", stamp


def applies(capture: Capture, name: str, config: Config) -> str | None:
    """None when stage `name` has something to work on; else why not, in a phrase. The video stages need takes
    with frames among those sync selects (after qc's verdicts): a recording with accelerometers only goes
    from qc straight to the analysis, and 3D needs at least two views. Without force, the run's magnify is left
    out: the analysis's 2D path writes a clip of each mode's band."""
    need = stage(name).needs_views
    if not need:
        return None
    takes = [t for t in capture.select_takes(config.sync.takes) if t.n_frames > 0]
    views = {t.view for t in takes}
    if not takes:
        unchecked = not capture.paths.qc_json.exists() and any(t.qc == "unchecked" for t in capture.manifest.takes)
        return f"no {config.sync.takes} take has video frames" + (" (qc has not run)" if unchecked else "")
    if len(views) < need:
        return f"3D needs takes from {need} views or more; the {config.sync.takes} takes with frames have {len(views)}"
    if name == "magnify" and not capture.manifest.has_force:
        return ("no force: the analysis's 2D path magnifies each mode's band itself (derived/analysis/clips/); "
                "`odsplat magnify` magnifies a band you choose")
    return None


# ------------------------------------------------------------------------------------------ running

class StageFailure(Exception):
    """A stage of `run` failed: `stage` names it, `cause` is its error in one line."""

    def __init__(self, stage: str, cause: BaseException | str):
        self.stage = stage
        self.cause = cause if isinstance(cause, str) else one_line(cause)
        super().__init__(f"stage {stage}: {self.cause}")

    def __reduce__(self):  # crosses process boundaries with its fields
        return type(self), (self.stage, self.cause)


class StageError(StageFailure, OdsplatError):
    """A stage refused its input (an odsplat error): one line, no traceback at the command line."""


class StageCrash(StageFailure, RuntimeError):
    """A stage failed unexpectedly (a bug, a library's error); chained to the original, whose traceback shows."""


@dataclass
class StageRun:
    stage: str
    status: str            # "ran", "current" or "n/a" (nothing to work on: `applies`)
    seconds: float
    summary: str
    reason: str = ""
    result: Any = None


def _unstamp(capture: Capture, name: str) -> None:
    stamp = capture.paths.stamp(name)
    if stamp.exists():
        stamp.unlink()
        fsync_path(stamp.parent)


def run_stage(capture: Capture, name: str, config: Config | None = None, settings: Any = None,
              executor: Executor | None = None, *, wait: bool = False) -> StageRun:
    """Run one stage now (whether or not it is current) and stamp it; `settings` replace the configuration's.
    `executor`: where a per-view stage (sync, magnify) sends each view's work (`executor.map`); by default the
    stage's own choice (magnify: a process pool of its `workers`). The capture's lock is held throughout
    (`odsplat.spine.lock`: another process holding it is named and refused, or waited for with `wait`).

    This is what the single-stage commands call, so their outputs are recorded like the pipeline's."""
    with capture_lock(capture, wait=wait):
        return _run_stage(capture, name, config, settings, executor)


def _run_stage(capture: Capture, name: str, config: Config | None, settings: Any,
               executor: Executor | None) -> StageRun:
    config = config or load_config(capture)
    if settings is not None:
        config = config.replace(name, settings)
    st = stage(name)
    prov = expected(capture, name, config)
    _unstamp(capture, name)  # first: a run killed from here on leaves the stage stale, never current
    remove_stale_temporaries(capture.paths.root)     # what killed runs left half-written
    started = time.perf_counter()
    s = config.settings(name)
    if executor is None:          # its own pools: no wider than the memory budget holds
        s, line = within_budget(name, s, Budget.of(config.run), *frames_and_views(capture))
        if line:
            log.info("%s", line)
    result = st.entry(capture, s, executor=executor) if executor is not None and st.per_view else st.entry(capture, s)
    seconds = time.perf_counter() - started
    summary = st.summary(result)
    outputs = output_identity(capture, st.outputs(capture, s))
    Stamp(prov, outputs, seconds, summary).write(capture, name)
    log.info("%s: ran in %.1f s", name, seconds)
    return StageRun(name, "ran", seconds, summary, result=result)


def frames_and_views(capture: Capture) -> tuple[int, int]:
    """The pixels of one frame of the capture's camera, and its number of takes (the per-view stages' tasks)."""
    cam = capture.manifest.camera
    takes = capture.manifest.takes
    return (cam.width_px or 0) * (cam.height_px or 0), len(takes)


@dataclass
class PipelineResult:
    capture: Path
    stages: list[StageRun] = field(default_factory=list)
    report: Path | None = None

    def text(self) -> str:
        """The stages' table, the analysis's result (modes, MAC) and where the report is."""
        lines = [f"{'stage':<12} {'status':<8} {'seconds':>8}"]
        for r in self.stages:
            lines.append(f"{r.stage:<12} {r.status:<8} {r.seconds:8.1f}" + (f"  ({r.reason})" if r.reason else ""))
        analysis = next((r for r in self.stages if r.stage == "analyze"), None)
        if analysis is not None and analysis.summary:
            lines += [line for line in analysis.summary.splitlines() if not line.startswith("-> ")]
        if self.report is not None:
            lines.append(f"report: {self.report}")
        return "\n".join(lines)


def _span(start: str | None, stop: str | None) -> Sequence[str]:
    i = STAGES.index(stage(start).name) if start else 0
    j = STAGES.index(stage(stop).name) if stop else len(STAGES) - 1
    if i > j:
        raise InputError("--from/--to", f"{start} comes after {stop} in the pipeline ({' -> '.join(STAGES)})")
    return STAGES[i:j + 1]


def run(capture: Capture, config: Config | None = None, *, start: str | None = None, stop: str | None = None,
        force: Iterable[str] = (), echo: Callable[[str], None] | None = None,
        executor: Executor | None = None, wait: bool = False) -> PipelineResult:
    """Run the stages from `start` to `stop` (default: all), each only when it is stale or forced; a stage from
    `start` on is always run (`--from`). `echo` gets a line as each stage begins and ends. `executor`: where the
    per-view stages send each view's work (`run_stage`). A stage that fails raises `StageError` (an odsplat
    error, one line) or `StageCrash` (anything else, chained to it), both naming the stage. The capture's lock
    is held throughout (`run_stage`; `wait`: wait for another holder instead of refusing)."""
    with capture_lock(capture, wait=wait):
        return _run(capture, config, start, stop, force, echo, executor)


def _run(capture: Capture, config: Config | None, start: str | None, stop: str | None, force: Iterable[str],
         echo: Callable[[str], None] | None, executor: Executor | None) -> PipelineResult:
    config = config or load_config(capture)
    say = echo or (lambda line: log.info("%s", line))
    forced = {stage(n).name for n in force}
    span = _span(start, stop)
    if start:
        forced.add(span[0])
    out = PipelineResult(capture.root)
    for name in span:
        skip = applies(capture, name, config)
        if skip is not None:
            _unstamp(capture, name)
            out.stages.append(StageRun(name, "n/a", 0.0, "", reason=skip))
            say(f"[{name}] does not apply: {skip}")
            continue
        current, why, stamp = _currency(capture, name, config)
        if current and name not in forced:
            out.stages.append(StageRun(name, "current", 0.0, stamp.summary))
            say(f"[{name}] current, skipped")
            continue
        why = "forced" if name in forced else why
        say(f"[{name}] running ({why})")
        try:
            done = run_stage(capture, name, config, executor=executor)
        except OdsplatError as exc:
            raise StageError(name, exc) from None
        except Exception as exc:
            storage = storage_error(exc)   # a full disk, a read-only folder: the machine's refusal, one line
            if storage is not None:
                raise StageError(name, storage) from None
            raise StageCrash(name, exc) from exc
        done.reason = why
        out.stages.append(done)
        say(f"[{name}] done in {done.seconds:.1f} s")
    if capture.paths.report_html.exists() and "report" in span:
        out.report = capture.paths.report_html
    return out


def status(capture: Capture, config: Config | None = None) -> list[tuple[str, bool, str]]:
    """(stage, current, why) for every stage, in order; a stage after a stale one is stale too (it will run)."""
    config = config or load_config(capture)
    out, stale = [], set()
    for name in STAGES:
        skip = applies(capture, name, config) if "qc" not in stale else None   # known once qc's verdicts are
        if skip is not None:
            out.append((name, True, f"does not apply: {skip}"))
            continue
        current, why = is_current(capture, name, config)
        behind = [up for up in stage(name).upstream(config) if up in stale]
        if current and behind:
            current, why = False, f"{', '.join(behind)} will run first"
        if not current:
            stale.add(name)
        out.append((name, current, why))
    return out


__all__ = ["BY_NAME", "GRAPH", "PipelineResult", "Stage", "StageCrash", "StageError", "StageFailure", "StageRun",
           "Stamp", "applies", "expected", "file_digest", "is_current", "output_identity", "outputs_unchanged", "run",
           "run_stage", "stage", "stage_settings", "status", "takes_identity"]
