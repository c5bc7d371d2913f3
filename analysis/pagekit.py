"""The report's plain values and its own files: a number as the page prints it (a dash where it is no finite number)
and a file of the analysis's own folder read for inlining (no link, nothing outside it), shared by report.py and
report_parts.py."""
from __future__ import annotations

import base64
import math
import os
import stat
from pathlib import Path, PurePosixPath, PureWindowsPath

from odsplat.spine.errors import InputError
from odsplat.spine.guard import check_inside

# The document is typed and checked (analysis/document.py): a field of the wrong kind never reaches the page. What
# a hand edit can still leave is a number that is no finite number, or an index that names nothing: those show as a
# dash, or as they stand.

DASH = "\u2013"    # where a number is missing or is no finite number


def finite(x: float | None) -> float | None:
    """x where it is a finite number, else None."""
    return x if x is not None and math.isfinite(x) else None


def index_in(i: int, n: int) -> int | None:
    """i as an index into a list of n, or None where it names none."""
    return i if 0 <= i < n else None


def num(x: float | None, fmt: str = ".3g", scale: float = 1.0) -> str:
    """x times scale formatted with fmt; a dash where x is no finite number."""
    v = None if x is None else x * scale
    if v is None or not math.isfinite(v):
        return DASH
    text = format(v, fmt)
    return format(0.0, fmt) if float(text) == 0 else text      # no "-0.0"


ANALYSIS_FOLDER = "derived/analysis"
SIGNATURES = {".png": (b"\x89PNG\r\n\x1a\n",), ".gif": (b"GIF87a", b"GIF89a")}
MEDIA = {".png": "image/png", ".gif": "image/gif", ".mp4": "video/mp4"}


def own_file(folder: Path, rel, where: str = ANALYSIS_FOLDER, writer: str = "the analysis") -> Path | str:
    """The file `rel` names in `folder`, or why it is not one of the folder's own (one line). Its own: a relative
    name of plain parts ("plots/frf.png": no `..`, `.` or empty part, no absolute path or drive, no backslash),
    no symbolic link on the way from `folder` down (the file included), a regular file, and inside `folder` once
    resolved. `where` names the folder in the line, `writer` what writes its files."""
    outside = f"not a file {writer} wrote (outside {where})"
    if not isinstance(rel, str) or not rel:
        return outside
    parts = rel.split("/")
    if (PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).anchor or "\\" in rel or "\0" in rel
            or any(p in ("", ".", "..") for p in parts)):
        return outside
    path = folder.joinpath(*parts)
    try:   # the parts are plain, so the one thing it can refuse is a link on the way
        check_inside(folder, path)
    except InputError:
        return f"not a file {writer} wrote (a symbolic link)"
    if not path.exists():
        return "not found"
    if not path.is_file():
        return "not a regular file"
    if not path.resolve().is_relative_to(folder.resolve()):
        return outside
    return path


def read_own(path: Path) -> bytes:
    """A file `own_file` accepted, opened without following a link (a link put in its place after the check makes
    the open fail) and read only if it is still a regular file."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    with os.fdopen(os.open(path, flags), "rb") as fh:
        if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
            raise OSError(f"{path}: not a regular file")
        return fh.read()


def data_uri(media: str, data: bytes) -> str:
    """A data: URI of bytes read here: base64 holds no character HTML would need escaped."""
    return f"data:{media};base64,{base64.b64encode(data).decode('ascii')}"




__all__ = ["ANALYSIS_FOLDER", "DASH", "MEDIA", "SIGNATURES", "data_uri", "finite", "index_in", "num", "own_file",
           "read_own"]
