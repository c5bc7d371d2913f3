"""Room to fail in: a reserve of disk space beside every HDF5 file odsplat writes, and the free-space check before a
stage with a known output size.

The HDF5 library does not survive a full disk: once a write has failed, closing the file crashes the process
(a segfault, at the close or at the interpreter's exit), and a take file left open for writing cannot be opened
again until its flags are cleared. So each HDF5 writer first sets aside `RESERVE_BYTES` of real disk space
(`Reserve`: an allocated file, `.odsplat-reserve.PID.tmp`, in the folder it writes) and gives it back just before
it closes the file, whether it finished or failed: the close then finds the room it needs, the file is left
consistent (a take's `.partial`, with every frame flushed, for `odsplat recover`), and the error reaches the
command line as one line. A disk too full for the reserve itself is refused before anything is written.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from odsplat.spine import errors
from odsplat.spine.errors import StorageError, free_bytes, human_bytes

log = logging.getLogger(__name__)

# What closing an HDF5 file may still write: its metadata and the dirty chunks in its datasets' caches, which
# `writing_h5` keeps to CHUNK_CACHE_BYTES each (HDF5 2.0's default is 8 MiB a dataset, more than the reserve).
# ODSPLAT_RESERVE_BYTES sets another size (the tests' small disks, to make a stage fail in the middle of its
# writing rather than before it).
CHUNK_CACHE_BYTES = 2 * 2**20
RESERVE_BYTES = int(os.environ.get("ODSPLAT_RESERVE_BYTES", 16 * 2**20))
_RESERVE = re.compile(r"\.odsplat-reserve\.(?P<pid>\d+)\.tmp")
_counter = iter(range(1 << 62))


def process_alive(pid: int) -> bool:
    """Whether process `pid` still runs (on this machine): whose temporaries and reserves may be removed."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _allocate(fd: int, size: int) -> None:
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as exc:
        if exc.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise
        block = b"\0" * 2**20              # a file system that cannot allocate: write the bytes
        for _ in range(size // len(block)):
            os.write(fd, block)


class Reserve:
    """`size` bytes of disk space held in `folder` until `release()`."""

    def __init__(self, folder: str | Path, size: int | None = None):
        size = RESERVE_BYTES if size is None else size
        self.folder = Path(folder)
        self.path: Path | None = None
        self._remove_stale()
        path = self.folder / f".odsplat-reserve.{os.getpid()}.tmp"
        if os.path.lexists(path):         # another writer of this process holds one here: a name of its own
            path = self.folder / f".odsplat-reserve.{os.getpid()}.tmp.{next(_counter)}"
        with folder_lock(self.folder):
            self._allocate(path, size)
        self.path = path

    def _allocate(self, path: Path, size: int) -> None:
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o600)
        except OSError as exc:
            if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                raise StorageError(self.folder, f"{exc.strerror.lower()}: odsplat needs to write here (copy the "
                                              "capture to a writable disk, or give --derived DIR)") from None
            raise
        try:
            _allocate(fd, size)
        except OSError as exc:
            os.close(fd)
            path.unlink(missing_ok=True)
            if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
                free = free_bytes(self.folder)
                free = "unknown" if free is None else human_bytes(free)
                raise StorageError(self.folder, f"no space left ({free} free): odsplat keeps "
                                              f"{human_bytes(size)} in reserve to close its files safely; free "
                                              "some space or write elsewhere (a stage: --derived DIR)") from None
            raise
        os.close(fd)

    def _remove_stale(self) -> None:
        with contextlib.suppress(OSError):
            for entry in os.scandir(self.folder):
                match = _RESERVE.match(entry.name)
                if match and not entry.is_symlink() and not process_alive(int(match["pid"])):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(entry.path)

    def release(self) -> None:
        if self.path is not None:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
            self.path = None


_leaked: list[Any] = []   # files whose close failed even so: kept referenced, never closed again


def close_h5(f: Any, reserve: Reserve | None) -> None:
    """Give back the reserve, then close the HDF5 file. A close that fails all the same is not tried again (the
    library would crash): the file object is kept, unclosed, and the error raised."""
    folder = reserve.folder if reserve is not None else None
    with folder_lock(folder) if folder is not None else contextlib.nullcontext():
        if reserve is not None:
            reserve.release()
        if errors._hdf5_dropped:   # an object's release failed on a full disk: closing may crash the library
            _leaked.append(f)
            raise StorageError(getattr(f, "filename", "an HDF5 file"), errors._hdf5_dropped[0].problem)
        try:
            f.close()
        except (OSError, RuntimeError) as exc:
            _leaked.append(f)
            log.warning("%s: not closed (%s)", getattr(f, "filename", "an HDF5 file"), " ".join(str(exc).split())[:300])
            raise


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Between the processes and threads writing into `folder` (sync's and magnify's pools): one at a time sets
    a reserve aside or gives one back and closes its file, so that the room a failing writer gives back for its
    close is not taken by another writer's new reserve. A `flock` on the folder itself: no file is made."""
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    except OSError:
        yield
        return
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


@contextlib.contextmanager
def writing_h5(path: str | Path, mode: str = "w", **kwargs: Any) -> Iterator[Any]:
    """An h5py file opened for writing with a `Reserve` in its folder, closed by `close_h5` however the block
    ends."""
    import h5py

    path = Path(path)
    reserve = Reserve(path.parent)
    try:
        f = h5py.File(path, mode, rdcc_nbytes=CHUNK_CACHE_BYTES, **kwargs)
    except BaseException:
        reserve.release()
        raise
    try:
        yield f
    except BaseException:
        with contextlib.suppress(OSError, RuntimeError):
            close_h5(f, reserve)
        raise
    close_h5(f, reserve)


def check_free(folder: Path, needed_bytes: float, what: str) -> None:
    """Refuse a stage that will write about `needed_bytes` into `folder` (the reserve added) when the disk has
    less free: one line, before anything is written."""
    free = free_bytes(folder)
    if free is None:
        return
    need = needed_bytes + RESERVE_BYTES
    if free < need:
        raise StorageError(folder, f"{human_bytes(need)} needed for {what}, {human_bytes(free)} free: free some "
                                 "space or write elsewhere (a stage: --derived DIR)")


__all__ = ["CHUNK_CACHE_BYTES", "RESERVE_BYTES", "Reserve", "check_free", "close_h5", "folder_lock", "process_alive",
           "writing_h5"]
