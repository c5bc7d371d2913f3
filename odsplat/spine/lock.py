"""One writer per capture: the lock every command that writes a capture's derived files (or its manifest) holds.

Two `odsplat run`s on one capture would each clear and rewrite the other's outputs. The lock is an advisory
`flock` on `derived/.odsplat.lock` (`DerivedPaths.lock`), which records who holds it (pid, host, command, since
when), so the second command can say so in one line, or wait for it (`--wait`). The holder removes the file as
it lets go, so a capture at rest holds none. The kernel releases a `flock` when its process dies, however it
dies, so the file a killed run leaves is simply taken over. The lock is re-entrant within a process
(`odsplat run` locks, and each stage it runs locks again).

A capture that cannot be written (a read-only folder) is not locked: nothing can change it, and the first write
a stage attempts is refused with one line naming the folder.
"""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from odsplat.spine.errors import InputError
from odsplat.spine.guard import link_error

log = logging.getLogger(__name__)

_held: dict[str, list[Any]] = {}   # lock path -> [fd, depth], the locks this process holds
_guard = threading.Lock()
POLL_S = 0.5


def _forget_in_child() -> None:
    """A forked child (a stage's process pool) shares its parent's lock: were it to keep the descriptor, the lock
    would outlive a killed parent for as long as the child lingers. The child closes its copy (the parent's lock
    stands: only `LOCK_UN` or the last copy's close releases it) and holds nothing."""
    global _guard
    for fd, _depth in _held.values():
        with contextlib.suppress(OSError):
            os.close(fd)
    _held.clear()
    _guard = threading.Lock()


os.register_at_fork(after_in_child=_forget_in_child)


def _holder(fd: int) -> dict[str, Any]:
    """What the lock file says of its holder ({} when it says nothing readable)."""
    try:
        text = os.pread(fd, 4096, 0).decode("utf-8", "replace")
        doc = json.loads(text) if text.strip() else {}
    except (OSError, ValueError):
        return {}
    return doc if isinstance(doc, dict) else {}


def describe_holder(doc: dict[str, Any]) -> str:
    if not doc:
        return "another odsplat process"
    parts = [f"pid {doc.get('pid', '?')}"]
    if doc.get("host") and doc.get("host") != socket.gethostname():
        parts.append(f"on {doc['host']}")
    if doc.get("command"):
        parts.append(f"`{doc['command']}`")
    if doc.get("since_utc"):
        parts.append(f"since {doc['since_utc']}")
    return "odsplat (" + ", ".join(parts) + ")"


def _record(fd: int) -> None:
    doc = {"pid": os.getpid(), "host": socket.gethostname(),
           "command": " ".join(["odsplat", *sys.argv[1:]])[:300],
           "since_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    os.ftruncate(fd, 0)
    os.pwrite(fd, (json.dumps(doc) + "\n").encode(), 0)


def _open(path: Path) -> int | None:
    """The lock file's descriptor, or None where the folder cannot be written (nothing to lock against)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        return os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
            log.debug("%s: not locked (%s): the capture cannot be written", path, exc.strerror)
            return None
        if exc.errno == errno.ELOOP:
            raise link_error(path) from None
        raise


@contextlib.contextmanager
def capture_lock(capture: Any, *, wait: bool = False, timeout_s: float | None = None) -> Iterator[None]:
    """Hold `capture`'s lock for the block. Held by another process: refuse with one line naming it, or with
    `wait` poll until it is free (`timeout_s`: give up after that long, with the same line)."""
    path = capture.paths.lock
    key = os.path.normpath(os.path.abspath(path))
    with _guard:
        mine = _held.get(key)
        if mine is not None:
            mine[1] += 1
    if mine is not None:
        try:
            yield
        finally:
            with _guard:
                mine[1] -= 1
        return
    fd = _locked_fd(path, capture, wait, timeout_s)
    if fd is None:
        yield
        return
    with _guard:
        _held[key] = [fd, 1]
    try:
        yield
    finally:
        with _guard:
            entry = _held[key]
            entry[1] -= 1
            release = entry[1] == 0
            if release:
                del _held[key]
        if release:   # the file goes while still locked: a command waiting on it sees it gone and opens anew
            with contextlib.suppress(OSError):
                os.unlink(path)
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)


def _locked_fd(path: Path, capture: Any, wait: bool, timeout_s: float | None) -> int | None:
    """The lock file's descriptor, locked; None where nothing can be written. The file a holder removes as it
    lets go may be the one this process was waiting on: then it is opened and locked again."""
    while True:
        fd = _open(path)
        if fd is None:
            return None
        try:
            _acquire(fd, capture, wait, timeout_s)
            try:
                current = os.stat(path, follow_symlinks=False).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                current = False
        except BaseException:
            os.close(fd)
            raise
        if current:
            _record(fd)
            return fd
        os.close(fd)


def _acquire(fd: int, capture: Any, wait: bool, timeout_s: float | None) -> None:
    started = time.monotonic()
    said = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.EINVAL):
                    log.warning("%s: this file system cannot lock (%s); going on unlocked", capture.root,
                                exc.strerror)
                    return
                raise
        holder = describe_holder(_holder(fd))
        waited = time.monotonic() - started
        if not wait or (timeout_s is not None and waited >= timeout_s):
            raise InputError(capture.root, f"in use by {holder}; run again when it has finished, or add --wait "
                                           "to wait for it")
        if not said:
            log.warning("%s: in use by %s; waiting for it", capture.root, holder)
            said = True
        time.sleep(POLL_S)
    stale = _holder(fd)
    if stale.get("pid") and stale.get("host") == socket.gethostname():
        log.info("%s: took over the lock left by pid %s, which is no longer running", capture.root, stale["pid"])


__all__ = ["capture_lock", "describe_holder"]
