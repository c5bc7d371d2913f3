"""Are a capture's raw takes whole? Every take's file is found, opened and read back through its per-chunk checksums
(`odsplat verify`); a quicker look (`file_problem`) tells `odsplat info` and `odsplat recover` of a listed take whose
file is missing or cut short."""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import h5py

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import TakeRecord
from odsplat.spine.store import Capture
from odsplat.spine.take_reader import TakeReader, damage_text, damaged_chunks

log = logging.getLogger(__name__)

# A take's state, worst first; "ok" and "no checksums" (an older take, read whole without error) are not faults.
STATES = ("missing", "truncated", "unreadable", "damaged", "unfinished", "unlisted", "no checksums", "ok")
_FINE = ("ok", "no checksums")
_BLOCK_CHUNKS = 64  # chunks read at once; a block that fails is read again chunk by chunk to name the damage
# What reading a take whose metadata (superblock, object headers, heaps, attributes) is damaged raises, from h5py
# or from parsing what it returns: KeyError (an object header that does not parse: "bad object header version
# number"), RuntimeError (visiting a group whose metadata checksum fails), OSError (a heap or attribute that
# does not read), ValueError (an attribute's JSON garbled), TypeError and IndexError (an attribute of the wrong
# type or shape). Measured by flipping each byte of a take's superblock and object headers in turn.
UNREADABLE_ERRORS = (KeyError, RuntimeError, OSError, ValueError, TypeError, IndexError, AttributeError)


@dataclass
class TakeCheck:
    """What `verify_take` found in one take file."""

    name: str
    file: str
    status: str                                  # one of STATES
    details: list[str] = field(default_factory=list)
    n_frames: int = 0
    n_samples: int = 0

    @property
    def ok(self) -> bool:
        return self.status in _FINE

    def line(self) -> str:
        head = f"{self.name}: {self.status.upper() if not self.ok else self.status}"
        if self.status == "ok":
            return f"{head} ({self.n_frames} frames, {self.n_samples} samples, every chunk's checksum holds)"
        return head + (": " + "; ".join(self.details) if self.details else "")


def file_problem(path: Path, record: TakeRecord | None = None) -> tuple[str, str] | None:
    """A listed take's file that is missing, cut short or not readable as a take: (state, what) without reading its
    data; None when it opens and holds as many frames and samples as the manifest lists."""
    if not path.exists():
        return "missing", f"{path}: listed in capture.json but the file is not there"
    try:
        with TakeReader(path) as r:
            n_frames, n_samples = r.n_frames, r.n_samples
    except InputError as exc:
        cut = re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", str(exc))
        if cut:
            return "truncated", f"{path}: cut short, holds {int(cut[1])} of its {int(cut[2])} bytes"
        return "unreadable", str(exc)
    except UNREADABLE_ERRORS as exc:
        return "unreadable", _metadata_damage(path, exc)
    if record is not None and (n_frames < record.n_frames or n_samples < record.n_samples):
        return "truncated", (f"{path}: holds {n_frames} frames and {n_samples} samples; capture.json lists "
                             f"{record.n_frames} and {record.n_samples}")
    return None


def _metadata_damage(path: Path, exc: BaseException) -> str:
    """One line for a take whose HDF5 metadata does not read (h5py's own message names what failed)."""
    text = " ".join(str(exc).split()).strip("'\"")[:200]
    return f"{path}: its HDF5 metadata (a header, heap or attribute) is damaged and does not read ({text})"


def listed_take_problems(capture: Capture) -> list[TakeCheck]:
    """The manifest's takes whose files are missing, cut short or unreadable (no data is read)."""
    out = []
    for record in capture.manifest.takes:
        problem = file_problem(capture.root / record.file, record)
        if problem is not None:
            out.append(TakeCheck(record.name, record.file, problem[0], [problem[1]]))
    return out


def _raw_datasets(f: h5py.File) -> list[h5py.Dataset]:
    """Every raw dataset of a take file: frames, their times and counter, DAQ and CAN channels."""
    found: list[h5py.Dataset] = []
    f.visititems(lambda _, obj: found.append(obj) if isinstance(obj, h5py.Dataset) else None)
    return found


def _damage(ds: h5py.Dataset) -> list[tuple[int, int]]:
    """Damaged chunks of a whole dataset, read a block of chunks at a time."""
    n = ds.shape[0] if ds.shape else 0
    block = (ds.chunks[0] if ds.chunks else max(n, 1)) * _BLOCK_CHUNKS
    bad = []
    for a in range(0, n, block):
        try:
            ds[a:a + block]
        except OSError:
            bad += damaged_chunks(ds, a, a + block)
    return bad


def verify_take(path: Path, record: TakeRecord | None = None, name: str | None = None) -> TakeCheck:
    """Read one take file whole through its checksums and say what is wrong with it, if anything."""
    name = name or (record.name if record else path.name.split(".")[0])
    file = record.file if record else str(path)
    problem = file_problem(path, record)
    if problem is not None:
        return TakeCheck(name, file, problem[0], [problem[1]])
    details, unchecked = [], []
    try:
        with TakeReader(path) as r:
            n_frames, n_samples = r.n_frames, r.n_samples
        with h5py.File(path, "r") as f:
            for ds in _raw_datasets(f):
                bad = _damage(ds)
                if bad:
                    details.append(f"{ds.name}: {damage_text(ds, bad)}")
                if not ds.fletcher32:
                    unchecked.append(ds.name)
    except InputError as exc:
        return TakeCheck(name, file, "unreadable", [str(exc)])
    except UNREADABLE_ERRORS as exc:
        return TakeCheck(name, file, "unreadable", [_metadata_damage(path, exc)])
    if details:
        status = "damaged"
    elif unchecked:
        status = "no checksums"
        details = [f"written without per-chunk checksums ({len(unchecked)} datasets, e.g. {unchecked[0]}); read "
                   "whole without error, but damage to its data cannot be detected"]
    else:
        status = "ok"
    return TakeCheck(name, file, status, details, n_frames, n_samples)


def verify_capture(capture: Capture) -> list[TakeCheck]:
    """Every take the manifest lists, read whole; then unfinished take files and finalised ones it does not list."""
    checks = []
    for record in capture.manifest.takes:
        check = verify_take(capture.root / record.file, record)
        if not check.ok:
            log.warning("%s", check.line())
        checks.append(check)
    for path in capture.partial_takes():
        checks.append(TakeCheck(path.name.split(".")[0], f"takes/{path.name}", "unfinished",
                                [f"{path}: its writer stopped before finalising; run `odsplat recover "
                                 f"{capture.root}`"]))
    for path in capture.unlisted_takes():
        check = verify_take(path, name=path.name.split(".")[0])
        detail = f"{path}: a finalised take capture.json does not list; run `odsplat recover {capture.root}`"
        checks.append(TakeCheck(check.name, f"takes/{path.name}", "unlisted" if check.ok else check.status,
                                [detail, *check.details], check.n_frames, check.n_samples))
    return checks


__all__ = ["STATES", "UNREADABLE_ERRORS", "TakeCheck", "file_problem", "listed_take_problems", "verify_capture",
           "verify_take"]
