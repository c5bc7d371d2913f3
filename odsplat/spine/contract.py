"""How a derived file describes itself, one way for every stage: its kind, its schema version, the capture it
belongs to, and the settings and input identities that produced it (`Provenance`). A reader refuses a file of
another kind, of a newer or older schema, or from another capture with one line naming the file.

The index files (JSON) open with the whole header; the data files beside them (`.npz`, `.h5`, `.ply`) record the
capture's id (`CAPTURE_KEY`), which their owners check with `check_capture`. `read_npz` is the one way a derived
`.npz` is read: whatever is wrong with the file (missing, empty, cut short, not a zip of arrays, damaged, holding
pickled objects, of another capture) becomes one line naming it."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import pickle
import struct
import uuid
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.errors import InputError
from odsplat.spine.manifest import check_regular_file, utc_now


def plain(value: Any) -> Any:
    """Settings as JSON-ready data: dataclasses as objects, tuples as lists, paths as strings."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return value.item()
    return value


def digest(data: Any) -> str:
    """A short, stable hash of JSON-like data (keys sorted)."""
    text = json.dumps(plain(data), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Provenance:
    """What produced a derived file. `run_id` is new on every run: it is the identity a downstream output
    records for this one, so a rerun upstream makes everything downstream stale."""

    kind: str
    schema_version: int
    capture_id: str
    settings: dict[str, Any]
    inputs: dict[str, str]
    run_id: str = field(default_factory=lambda: uuid.uuid4().hex[:16])
    created_utc: str = field(default_factory=utc_now)

    @property
    def fingerprint(self) -> str:
        """The hash of what decides the result: kind, schema, capture, settings and inputs (not the run)."""
        return digest([self.kind, self.schema_version, self.capture_id, self.settings, self.inputs])

    def header(self) -> dict[str, Any]:
        """The self-description every derived JSON file opens with."""
        return {"kind": self.kind, "schema_version": self.schema_version, "capture_id": self.capture_id,
                "provenance": {"settings": self.settings, "inputs": self.inputs, "run_id": self.run_id,
                               "fingerprint": self.fingerprint, "created_utc": self.created_utc}}


def describe(capture_id: str, kind: str, schema_version: int, settings: Any,
             inputs: dict[str, str] | None = None) -> Provenance:
    return Provenance(kind, schema_version, capture_id, plain(settings) if settings is not None else {},
                      dict(inputs or {}))


def check(doc: Any, path: str | Path, *, kind: str, schema_version: int, capture_id: str | None) -> Provenance:
    """The provenance of a derived file's parsed header, or one clear line on what is wrong with it."""
    if not isinstance(doc, dict):
        raise InputError(path, f"not an {kind} file (expected a JSON object)")
    got = doc.get("kind")
    if got is None and "format" in doc:   # the self-description before odsplat.spine.contract
        raise InputError(path, f"written by an older odsplat ({doc['format']!r} version {doc.get('version')!r}); "
                               "run its stage again")
    if got != kind:
        raise InputError(path, f"not an {kind} file (its kind is {got!r})")
    version = doc.get("schema_version")
    if isinstance(version, str):   # "1.0": the poses file before odsplat.spine.contract
        raise InputError(path, f"schema {version!r} is older than this odsplat writes ({schema_version}); "
                               "run its stage again")
    if not isinstance(version, int) or isinstance(version, bool):
        raise InputError(path, f"schema_version: expected an integer, got {version!r}")
    if version > schema_version:
        raise InputError(path, f"schema {version} is newer than this odsplat reads ({kind} schema "
                               f"{schema_version}); update odsplat")
    if version < schema_version:
        raise InputError(path, f"schema {version} is older than this odsplat writes ({schema_version}); "
                               "run its stage again")
    other = doc.get("capture_id")
    if capture_id is not None and other != capture_id:
        raise foreign(path, other, capture_id)
    prov = doc.get("provenance") or {}
    if not isinstance(prov, dict):
        raise InputError(path, "provenance: expected an object")
    return Provenance(kind, version, str(other), prov.get("settings") or {}, prov.get("inputs") or {},
                      run_id=str(prov.get("run_id", "")), created_utc=str(prov.get("created_utc", "")))


# ------------------------------------------------------------------------------------------ derived data files

CAPTURE_KEY = "capture_id"   # the key (.npz), attribute (.h5) or comment word (.ply) that holds the capture's id


def foreign(path: str | Path, other: Any, capture_id: str) -> InputError:
    """The one refusal of a derived file that records another capture's id."""
    return InputError(path, f"belongs to another capture (id {other!r}, not this capture's {capture_id!r}: copied "
                            "from another capture?); run its stage again")


def check_capture(found: Any, path: str | Path, capture_id: str | None) -> None:
    """A data file's recorded capture id (None: it records none) against this capture's (None: not known, nothing
    to check). A file of another capture is refused; one that records none was written before odsplat recorded
    it, and its index file (which does) vouches for it."""
    if isinstance(found, bytes):
        found = found.decode(errors="replace")
    if isinstance(found, np.ndarray):
        found = str(found.item()) if found.shape == () else repr(found.tolist())
    if capture_id is not None and found is not None and found != capture_id:
        raise foreign(path, found, capture_id)


# What np.load and zipfile raise on a file that is not a whole .npz of plain arrays: cut short or empty (EOFError,
# BadZipFile), a damaged member (BadZipFile's CRC, zlib.error), another format or pickled objects (ValueError,
# UnpicklingError), a garbled array header (ValueError, struct.error, MemoryError for an absurd shape), an
# unsupported zip feature (NotImplementedError, RuntimeError).
NPZ_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError,
              struct.error, MemoryError, NotImplementedError, RuntimeError, TypeError)


def read_npz(path: str | Path, *, missing: str, capture_id: str | None = None) -> dict[str, np.ndarray]:
    """Every array of a derived `.npz`, read whole (each member through its CRC) without unpickling anything,
    its recorded capture id checked against `capture_id` and left out of the result. One line naming the file when
    it is missing (`missing` says what was expected there), empty, cut short, not an `.npz`, damaged or another
    capture's."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, missing)
    check_regular_file(path, ".npz file")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes); run its stage again")
    with open(path, "rb") as fh:
        head = fh.read(8)
    if not head.startswith(b"PK"):   # every zip archive, so every .npz, begins so
        raise InputError(path, f"not an .npz file (a zip archive of arrays): it begins {head!r}; run its stage again")
    try:
        with np.load(path, allow_pickle=False) as z:   # a zip: an NpzFile
            arrays = {k: z[k] for k in z.files}
    except NPZ_ERRORS as exc:
        text = " ".join(str(exc).split())[:200]
        raise InputError(path, f"not a readable .npz file, cut short or damaged ({type(exc).__name__}: {text}); "
                               "run its stage again") from None
    found = arrays.pop(CAPTURE_KEY, None)
    check_capture(found, path, capture_id)
    return arrays


def numeric(arrays: Mapping[str, np.ndarray], key: str, path: str | Path,
            shape: tuple[int | None, ...] | None = None) -> np.ndarray:
    """arrays[key], checked: present, of numbers (integers or floats, not text or objects), of `shape` where given
    (None matches any length on that axis). One line naming the file and the key otherwise."""
    if key not in arrays:
        raise InputError(path, f"no {key} (not the file its stage writes); run its stage again")
    a = np.asarray(arrays[key])
    if a.dtype.kind not in "iuf":
        raise InputError(f"{path}: {key}", f"expected numbers, got {a.dtype} data; run its stage again")
    if shape is not None and (a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape))):
        want = "(" + ", ".join("any" if n is None else str(n) for n in shape) + ("," if len(shape) == 1 else "") + ")"
        raise InputError(f"{path}: {key}", f"expected shape {want}, got {a.shape}; run its stage again")
    return a
