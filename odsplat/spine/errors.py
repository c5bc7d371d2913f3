"""Exceptions that carry the file, field or device at fault, so a user sees one clear line."""
from __future__ import annotations

import errno
import logging
import os
import re
import shutil
import sys
from os import PathLike
from typing import Any


class OdsplatError(Exception):
    """Base class of every error odsplat raises on purpose."""


class InputError(OdsplatError, ValueError):
    """Bad input: names the source (file, field or device) and what was expected."""

    def __init__(self, source: str | PathLike, problem: str):
        self.source = str(source)
        self.problem = problem
        super().__init__(f"{self.source}: {problem}")

    def __reduce__(self):  # raised in a worker process, it must cross back with both fields
        return type(self), (self.source, self.problem)


class SchemaError(InputError):
    """A file written by a newer, unknown or foreign schema."""


class StorageError(InputError):
    """The machine refused to store: a full disk, a read-only or forbidden folder (not the input's fault)."""


class IncompleteTakeError(InputError):
    """A take that was never finalised (its writer died); it must be recovered explicitly."""


def one_line(exc: BaseException) -> str:
    """An error in one line: odsplat's own as they are (they name their culprit), others with their type."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, OdsplatError) else f"{type(exc).__name__}: {text}" if text else type(exc).__name__


# What the machine refuses rather than the input: a full disk, a read-only or forbidden folder.
_STORAGE = {errno.ENOSPC: "no space left", errno.EDQUOT: "disk quota exceeded", errno.EFBIG: "file too large for "
            "this file system or limit", errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
            errno.EPERM: "operation not permitted"}
_H5_ERRNO = re.compile(r"errno = (\d+)")
_H5_NAME = re.compile(r"(?:file)?name = '([^']*)'")
_NEEDS = {errno.ENOSPC: "free some space or write elsewhere (a stage: --derived DIR)",
          errno.EDQUOT: "free some space or write elsewhere (a stage: --derived DIR)",
          errno.EFBIG: "write elsewhere (a stage: --derived DIR)",
          errno.EROFS: "odsplat writes its results under derived/: copy the capture to a writable disk, or give "
                       "--derived DIR",
          errno.EACCES: "odsplat needs to write there: fix the permissions, or give --derived DIR",
          errno.EPERM: "odsplat needs to write there: fix the permissions, or give --derived DIR"}


def free_bytes(path: str | PathLike) -> int | None:
    """The bytes free on the file system `path` is on (or would be: its nearest folder that exists), None where
    that cannot be read."""
    folder = os.path.abspath(path)
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def human_bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.3g} {unit}"
        n /= 1000
    return f"{n} B"


def storage_error(exc: BaseException) -> StorageError | None:
    """The storage problem behind `exc` (itself, or what it was raised from or during) as one line naming the file:
    a full disk, a read-only or forbidden folder, an HDF5 write that failed on one of them. None for anything else."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        code, name = (exc.errno, exc.filename) if isinstance(exc, OSError) else (None, None)
        if isinstance(exc, (OSError, RuntimeError)):
            if code is None or name is None:   # h5py puts the C library's errno and the file's name in its message
                text = str(exc)
                found = _H5_ERRNO.search(text)
                code = code if code is not None else int(found[1]) if found else None
                named = _H5_NAME.search(text)
                name = name if name is not None else named[1] if named else None
                if code is None and "No space left" in text:
                    code = errno.ENOSPC
            if code in _STORAGE:
                where = str(name) if name else "a file odsplat was writing"
                free = free_bytes(name) if name and code in (errno.ENOSPC, errno.EDQUOT) else None
                free = f", {human_bytes(free)} free" if free is not None else ""
                return StorageError(where, f"{_STORAGE[code]}{free}: {_NEEDS[code]}")
        if isinstance(exc, StorageError):
            return exc
        if isinstance(exc, OdsplatError):   # already one line naming its culprit
            return None
        exc = exc.__cause__ or (None if exc.__suppress_context__ else exc.__context__)
    return None


_hdf5_dropped: list[StorageError] = []   # objects whose release failed on a storage error (`quiet_hdf5_releases`)


def quiet_hdf5_releases() -> None:
    """An h5py object released while its file cannot be written (a full disk: a dataset's cached chunks have
    nowhere to go) fails where Python can only print the error: Cython prints its traceback (`sys.excepthook`),
    then "Exception ignored" (`sys.unraisablehook`). Such a failure is logged in one line instead and remembered:
    `close_h5` then refuses to close any more files (the library may crash doing it) and the process ends as
    `exit_if_hdf5_unclosed` says. The file was being written under a temporary name and is discarded; the stage's
    error line says why. Anything else is printed as before. Set in each process that writes HDF5 (the command
    line, the pool's workers)."""
    if getattr(sys.unraisablehook, "_odsplat", False):
        return
    previous_unraisable, previous_except = sys.unraisablehook, sys.excepthook

    def released(exc: BaseException | None, tb: Any) -> StorageError | None:
        while tb is not None:
            if tb.tb_frame.f_code.co_filename.endswith("_objects.pyx"):
                return storage_error(exc) if exc is not None else None
            tb = tb.tb_next
        return None

    def unraisable(args: Any) -> None:
        storage = released(args.exc_value, args.exc_traceback)
        if storage is None:
            previous_unraisable(args)
            return
        _hdf5_dropped.append(storage)
        logging.getLogger("odsplat.spine.space").warning("an HDF5 object not released: %s", storage)

    def excepthook(kind: type, exc: BaseException, tb: Any) -> None:
        if released(exc, tb) is None:   # the first print of the same failure: the unraisable hook logs it
            previous_except(kind, exc, tb)

    unraisable._odsplat = True  # type: ignore[attr-defined]
    sys.unraisablehook, sys.excepthook = unraisable, excepthook


def exit_if_hdf5_unclosed() -> None:
    """Before exiting on a storage error: a file whose close failed even with the space reserve given back
    (`odsplat.spine.space`) makes the HDF5 library crash at the interpreter's exit, when it closes what is still open.
    The process then ends at once (its error line written, its streams flushed), skipping that exit."""
    space = sys.modules.get("odsplat.spine.space")
    if (space is not None and space._leaked) or _hdf5_dropped:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(2)
