"""Many captures through the pipeline at once (`odsplat batch`), on Dask distributed: a local cluster of worker
processes by default, or any running scheduler by its address.

One task per capture runs `pipeline.run` on a worker; inside it the per-view stages (sync's aligned frames, one
task per take; magnify, one task per view) send each view's work back to the cluster through `ClusterExecutor`,
so one large capture spreads over the workers too. Each view's task writes only its own file, and the capture's
task writes the stage's index once its views are done, through the same atomic writers as `odsplat run`. A
capture that fails is reported with the stage and one line and the others go on; the pipeline's skip rule makes
a rerun do only what failed or is stale.
"""
from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from distributed import WorkerPlugin

from odsplat.app.config import load_config
from odsplat.app.pipeline import StageFailure, run
from odsplat.spine.errors import InputError, one_line
from odsplat.spine.store import Capture

log = logging.getLogger(__name__)

TOPIC = "odsplat-batch"    # the workers' progress events (a stage begun, done, skipped)
VIEW_PRIORITY = 10         # a capture's views go before the next capture's pipeline: captures finish early


# ------------------------------------------------------------------------------------------ per-view tasks

class ClusterExecutor(Executor):
    """`map` over a Dask cluster for the per-view work of a capture whose pipeline runs in a task on a worker.

    Each call is a task of its own (not cached: `pure=False`), ranked before captures still waiting. While the
    capture's task waits for them it leaves the worker's thread pool (`secede`, then `rejoin`), so a worker
    with one thread runs a view while the capture that sent it waits. On a failure every other view is waited
    for before the error is raised, as a process pool's `with` does, so no view's file is written after the
    stage has cleaned up its outputs."""

    def __init__(self, client: Any):
        self._client = client

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Any:
        return self._client.get_executor(pure=False, retries=0).submit(fn, *args, **kwargs)

    def map(self, fn: Callable[..., Any], *iterables: Iterable[Any], timeout: float | None = None,
            chunksize: int = 1) -> Iterator[Any]:
        futures = self._client.map(fn, *iterables, pure=False, priority=VIEW_PRIORITY)
        return self._results(futures)

    def _results(self, futures: list[Any]) -> Iterator[Any]:
        from distributed import rejoin, secede, wait

        secede()
        try:
            for f in futures:
                try:
                    yield f.result()
                except BaseException:
                    wait(futures)
                    raise
        finally:
            rejoin()


class _QuietBars(WorkerPlugin):
    """A worker plugin for the local cluster: no progress bars in its workers (the stages' tqdm bars of several
    workers would interleave on the batch's terminal, which reports a line per stage instead)."""

    name = "odsplat-quiet-bars"

    def setup(self, worker: Any) -> None:
        _quiet_bars()


def _quiet_bars() -> None:
    import tqdm.std

    init = tqdm.std.tqdm.__init__
    if getattr(init, "_odsplat_quiet", False):
        return

    def quiet(self: Any, *args: Any, **kwargs: Any) -> None:
        kwargs["disable"] = True
        init(self, *args, **kwargs)

    quiet._odsplat_quiet = True  # type: ignore[attr-defined]
    tqdm.std.tqdm.__init__ = quiet


# ------------------------------------------------------------------------------------------ one capture

@dataclass
class CaptureOutcome:
    """One capture's pipeline in the batch: each stage's status and seconds, or the stage that failed and why."""

    capture: str
    ok: bool
    stages: list[tuple[str, str, float]] = field(default_factory=list)   # (stage, ran/current/n/a, seconds)
    failed_stage: str | None = None     # the stage that failed ("config" before any stage; "worker": the task died)
    error: str | None = None            # why, in one line
    seconds: float = 0.0

    def line(self) -> str:
        if not self.ok:
            return f"{self.capture}: FAILED in {self.failed_stage}: {self.error}"
        ran = [s for s, status, _ in self.stages if status == "ran"]
        return (f"{self.capture}: ok in {self.seconds:.1f} s ("
                + (f"ran {', '.join(ran)}" if ran else "everything current") + ")")


def run_capture(root: str, *, start: str | None = None, stop: str | None = None, force: Sequence[str] = (),
                sets: Sequence[str] = (), config_path: str | None = None) -> CaptureOutcome:
    """The task of one capture, on a worker: its pipeline, with the per-view stages' work sent to the cluster and
    each stage's progress sent to the batch as an event. Failures come back as the outcome, never raised."""
    from distributed import get_client, get_worker

    started = time.perf_counter()
    worker = get_worker()
    name = Path(root).name

    def echo(line: str) -> None:
        worker.log_event(TOPIC, {"capture": name, "line": line})

    out = CaptureOutcome(root, ok=False)
    try:
        cap = Capture.open(root)
        config = load_config(cap, path=None if config_path is None else Path(config_path), sets=tuple(sets))
    except Exception as exc:
        out.failed_stage, out.error = "config", one_line(exc)
    else:
        try:
            result = run(cap, config, start=start, stop=stop, force=force, echo=echo,
                         executor=ClusterExecutor(get_client()))
        except StageFailure as exc:
            out.failed_stage, out.error = exc.stage, exc.cause
        except Exception as exc:   # outside any stage: still this capture's alone
            out.failed_stage, out.error = "pipeline", one_line(exc)
        else:
            out.ok = True
            out.stages = [(r.stage, r.status, r.seconds) for r in result.stages]
    out.seconds = time.perf_counter() - started
    return out


# ------------------------------------------------------------------------------------------ the batch

@dataclass
class BatchResult:
    outcomes: list[CaptureOutcome]
    seconds: float
    dashboard: str | None = None

    @property
    def failed(self) -> list[CaptureOutcome]:
        return [o for o in self.outcomes if not o.ok]

    def text(self) -> str:
        lines = [o.line() for o in self.outcomes]
        lines.append(f"{len(self.outcomes) - len(self.failed)} of {len(self.outcomes)} capture(s) ok, "
                     f"{len(self.failed)} failed, in {self.seconds:.1f} s")
        return "\n".join(lines)


def _captures(paths: Iterable[str | Path]) -> tuple[list[str], dict[str, CaptureOutcome]]:
    """Absolute capture folders, each once (two tasks must never write the same capture), in the order given; and
    the folders that are no capture, each with its outcome (it fails alone: the others still run)."""
    out: list[str] = []
    refused: dict[str, CaptureOutcome] = {}
    for p in paths:
        root = str(Path(p).resolve())
        if root in out or root in refused:
            continue
        if not (Path(root) / "capture.json").is_file():
            refused[root] = CaptureOutcome(root, ok=False, failed_stage="config",
                                           error=f"{p}: not a capture (no capture.json)")
        else:
            out.append(root)
    if not out and not refused:
        raise InputError("CAPTURE", "no captures given")
    return out, refused


def run_batch(captures: Iterable[str | Path], *, scheduler: str | None = None, workers: int | None = None,
              start: str | None = None, stop: str | None = None, force: Sequence[str] = (),
              sets: Sequence[str] = (), config_path: str | Path | None = None,
              echo: Callable[[str], None] | None = None, dashboard_address: str = ":8787") -> BatchResult:
    """Run the pipeline on every capture, a task each, on a Dask cluster: `scheduler` (an address such as
    tcp://host:8786, whose workers see the captures at the same paths and have odsplat installed), or a
    LocalCluster of `workers` processes (default: one per core) with one thread each. `start`, `stop`, `force`,
    `sets` and `config_path` are `odsplat run`'s. `echo` gets the dashboard's address, a line per capture and
    stage as they finish, and a line per capture at its end."""
    from distributed import Client, LocalCluster, as_completed

    say = echo or (lambda line: log.info("%s", line))
    roots, refused = _captures(captures)
    order = [str(Path(p).resolve()) for p in captures]
    order = [r for i, r in enumerate(order) if r not in order[:i]]
    lock = threading.Lock()
    for outcome in refused.values():
        say(outcome.line())
    if not roots:
        return BatchResult([refused[r] for r in order], 0.0, None)

    def tell(line: str) -> None:
        with lock:
            say(line)

    def progress(event: tuple[float, dict[str, str]]) -> None:
        msg = event[1]
        if " running " not in msg["line"]:
            tell(f"{msg['capture']}: {msg['line']}")

    started = time.perf_counter()
    cluster = None
    if scheduler is None:
        n = workers or os.cpu_count() or 1
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=dashboard_address)
        client = Client(cluster)
        client.register_plugin(_QuietBars())
    else:
        if workers is not None:
            raise InputError("--workers", "sets the local cluster's size; a running scheduler has its own workers")
        client = Client(scheduler)
    try:
        dashboard = client.dashboard_link
        tell(f"dashboard: {dashboard}")
        client.subscribe_topic(TOPIC, progress)
        futures = {}
        for root in roots:
            key = f"odsplat-pipeline-{Path(root).name}-{uuid.uuid4().hex[:8]}"
            futures[client.submit(run_capture, root, start=start, stop=stop, force=tuple(force), sets=tuple(sets),
                                  config_path=None if config_path is None else str(Path(config_path).resolve()),
                                  key=key, pure=False)] = root
        done: dict[str, CaptureOutcome] = {}
        for fut in as_completed(futures):
            root = futures[fut]
            try:
                outcome = fut.result()
            except Exception as exc:   # the task itself was lost: its worker died, or the scheduler went away
                outcome = CaptureOutcome(root, ok=False, failed_stage="worker", error=one_line(exc))
            done[root] = outcome
            tell(outcome.line())
        client.unsubscribe_topic(TOPIC)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    done.update(refused)
    return BatchResult([done[r] for r in order], time.perf_counter() - started, dashboard)


__all__ = ["BatchResult", "CaptureOutcome", "ClusterExecutor", "run_batch", "run_capture"]
