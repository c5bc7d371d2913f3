"""Atomic file writing: a file appears whole at its name or not at all (fsync, rename, fsync the folder), the
temporaries of killed writers are cleared, and the frames' HDF5 compression that every frame writer shares."""
from __future__ import annotations

import contextlib
import logging
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import hdf5plugin

from odsplat.spine.guard import link_error
from odsplat.spine.space import process_alive

log = logging.getLogger(__name__)


def frame_compression() -> Mapping[str, Any]:
    """The HDF5 filter of every frame dataset (takes and derived frame files): Blosc zstd level 3, bitshuffle."""
    return hdf5plugin.Blosc(cname="zstd", clevel=3, shuffle=hdf5plugin.Blosc.BITSHUFFLE)


def fsync_path(path: Path) -> None:
    """fsync a file or a directory (the latter makes a rename durable)."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_TEMPORARY = re.compile(r"\..+\.(?P<pid>\d+)\.tmp(\.\w+)?")   # what atomic_path names its temporaries


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """A temporary path beside `path` to write; on a clean exit the file is fsynced and renamed over `path` (and
    the directory fsynced), on an error removed. A crash leaves either the old file or the new one, never half.
    `suffix` ends the temporary's name, for writers that choose a format by it (OpenCV's mp4: ".mp4").
    A folder that is a symbolic link is refused (nothing is written through a link), and whatever lies at the
    temporary's name (a dead process's file with this pid, or a link planted there) is removed first, so the
    writer creates a new plain file."""
    path = Path(path)
    if path.parent.is_symlink():
        raise link_error(path.parent)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    if os.path.lexists(tmp):
        tmp.unlink()
    try:
        yield tmp
        fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    fsync_path(path.parent)


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Remove the temporaries `atomic_path` leaves when its writer is killed (`.NAME.PID.tmp[SUFFIX]`, in `folder`
    and below) whose process is gone; a live writer's are left alone. Links are neither followed nor removed, a
    linked `folder` is not walked. Returns what was removed."""
    folder = Path(folder)
    removed: list[Path] = []
    if folder.is_symlink() or not folder.is_dir():
        return removed
    for here, _dirs, files in os.walk(folder, followlinks=False):
        for name in files:
            tmp = Path(here) / name
            match = _TEMPORARY.fullmatch(name)
            if match is None or tmp.is_symlink() or process_alive(int(match["pid"])):
                continue
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
                removed.append(tmp)
    if removed:
        log.info("removed %d temporaries of killed runs under %s", len(removed), folder)
    return removed


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside `path`, made durable and renamed over `path` on a clean exit (`atomic_path`)."""
    with atomic_path(path) as tmp, open(tmp, mode) as fh:
        yield fh


def atomic_write_text(path: Path, text: str) -> None:
    """Write text to `path` so that a crash leaves either the old file or the new one, never half."""
    with atomic_open(path, "w") as fh:
        fh.write(text)
