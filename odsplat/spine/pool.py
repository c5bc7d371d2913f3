"""The process pool the stages spread their per-view work over, whose workers die with the process that made it.

A `ProcessPoolExecutor`'s workers wait on a queue whose other end they hold themselves (fork), so when the run is
killed (`kill -9`, the out-of-memory killer) they never see it close and wait forever, each holding the memory of
its view. Each worker here asks the kernel to kill it when its parent dies (Linux's PR_SET_PDEATHSIG), and leaves at
once where the parent is already gone. Elsewhere the pool is Python's own.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
import signal
from concurrent.futures import ProcessPoolExecutor

from odsplat.spine.errors import quiet_hdf5_releases

_PR_SET_PDEATHSIG = 1


def process_pool(workers: int, fresh: bool = False) -> ProcessPoolExecutor:
    """A pool of `workers` processes that end with this one. Create and use it in one thread: the kernel ties the
    workers' lives to the thread that starts them (submit starts them). `fresh`: processes started anew (spawn)
    rather than forked, for a caller whose threads (torch's OpenMP pool, once it has run) a fork would copy
    half-held: a forked worker then waits on them forever."""
    context = multiprocessing.get_context("spawn") if fresh else None
    return ProcessPoolExecutor(workers, mp_context=context, initializer=_die_with, initargs=(os.getpid(),))


def _die_with(parent_pid: int) -> None:
    quiet_hdf5_releases()   # a spawned worker starts without the command line's hooks
    name = ctypes.util.find_library("c")
    if name is not None:
        try:
            ctypes.CDLL(name, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):   # no prctl here (not Linux): the pool is Python's own
            pass
    if os.getppid() != parent_pid:          # the parent died before the request took effect
        os._exit(1)
