"""The run's memory budget (`[run] memory_gb`): how many processes the per-view work runs at once (sync's and
magnify's pools, the linear motion's readers), from what one of them holds at the capture's frame size, so that a
large capture on a small machine runs slower instead of running out of memory.

Every other stage streams in fixed chunks whatever the budget (docs/scaling.md has each stage's peak); what the
budget sets is the pools' width, which multiplies a process's working memory. It changes only settings that do not
change the result (`workers`, the stage table's `volatile`), so a run under another budget is still current.

A process's working memory, measured (docs/scaling.md, the seed's capture at 27 x 640 x 1024^2 on 2 cores):
sync holds about SYNC_BASE_BYTES plus SYNC_PER_BUDGET x its own `max_memory_mb`, magnify about MAGNIFY_BASE_BYTES
plus MAGNIFY_PER_PX bytes a pixel of the frame (the steerable pyramid's complex bands), the linear motion's reader
about LINEAR_BASE_BYTES plus LINEAR_PER_PX_FRAME bytes a pixel of each frame of its chunk."""
from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from typing import Any

from odsplat.spine.checks import Range, check_fields, maybe

log = logging.getLogger(__name__)

SYNC_BASE_BYTES = 0.3e9
SYNC_PER_BUDGET = 2.0       # sync's peak a process, in units of its max_memory_mb (0.82 GB at 256 MB)
MAGNIFY_BASE_BYTES = 0.4e9
MAGNIFY_PER_PX = 2800.0     # one 1024^2 view: 3.35 GB
LINEAR_BASE_BYTES = 0.5e9
LINEAR_PER_PX_FRAME = 28.0  # the linear motion's reader: a chunk of frames as float32 and float64 copies
MACHINE_SHARE = 0.5         # the default budget: this share of the machine's memory


@dataclass(frozen=True)
class RunSettings:
    memory_gb: float | None = None      # the run's working memory; None: MACHINE_SHARE of the machine's

    def __post_init__(self) -> None:
        check_fields(self, {"memory_gb": maybe(Range(above=0, at_most=1e6))})


def machine_memory_bytes() -> float:
    """The machine's physical memory (its cgroup's limit where lower)."""
    total = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    try:
        with open("/sys/fs/cgroup/memory.max") as f:
            text = f.read().strip()
        if text.isdigit():
            total = min(total, float(text))
    except OSError:
        pass
    return total


@dataclass(frozen=True)
class Budget:
    bytes: float
    why: str

    @classmethod
    def of(cls, run: RunSettings) -> Budget:
        if run.memory_gb is not None:
            return cls(run.memory_gb * 1e9, "as set (run.memory_gb)")
        machine = machine_memory_bytes()
        return cls(MACHINE_SHARE * machine, f"{MACHINE_SHARE:.0%} of this machine's {machine / 1e9:.1f} GB")


def process_bytes(stage: str, settings: Any, frame_px: int) -> float | None:
    """What one process of a per-view stage holds at this frame size; None for the other stages."""
    if stage == "sync":
        return SYNC_BASE_BYTES + SYNC_PER_BUDGET * settings.max_memory_mb * 1e6
    if stage == "magnify":
        return MAGNIFY_BASE_BYTES + MAGNIFY_PER_PX * frame_px
    if stage == "reconstruct" and settings.motion == "linear":
        return LINEAR_BASE_BYTES + LINEAR_PER_PX_FRAME * settings.linear.chunk_frames * frame_px
    return None


def _pool(stage: str, settings: Any) -> Any:
    """The settings that hold the stage's pool width (`workers`)."""
    return settings.linear if stage == "reconstruct" else settings


def within_budget(stage: str, settings: Any, budget: Budget, frame_px: int, n_views: int) -> tuple[Any, str | None]:
    """The stage's settings with its pool no wider than the budget holds (where its `workers` is left unset), and
    a line saying so; a pool set wider than the budget is kept, and the line warns."""
    each = process_bytes(stage, settings, frame_px)
    if each is None:
        return settings, None
    fits = max(1, int(budget.bytes // each))
    if stage == "magnify" and not settings.every_view:     # the views to watch: the first, or those named
        n_views = min(n_views, len(settings.takes or settings.views) or 1)
    pool = _pool(stage, settings)
    wanted = pool.workers or min(os.cpu_count() or 1, max(n_views, 1))   # the stages' own default
    if pool.workers is not None:
        if pool.workers > fits:
            return settings, (f"{stage}: {pool.workers} processes of about {each / 1e9:.2f} GB each pass the "
                              f"memory budget of {budget.bytes / 1e9:.1f} GB ({budget.why}); {fits} fit")
        return settings, None
    workers = min(wanted, fits)
    line = f"{stage}: {workers} process{'es' if workers > 1 else ''} of about {each / 1e9:.2f} GB"
    if workers < wanted:
        line += f" (not {wanted}: the memory budget is {budget.bytes / 1e9:.1f} GB, {budget.why})"
    if each > budget.bytes:
        line += f"; one alone passes the budget of {budget.bytes / 1e9:.1f} GB ({budget.why})"
    narrowed = dataclasses.replace(pool, workers=workers)
    if stage == "reconstruct":
        return dataclasses.replace(settings, linear=narrowed), line
    return narrowed, line


__all__ = ["Budget", "RunSettings", "machine_memory_bytes", "process_bytes", "within_budget"]
