"""How a derived file describes itself, one way for every stage: its kind, its schema version, the capture it
belongs to, and the settings and input identities that produced it (`Provenance`). A reader refuses a file of
another kind, of a newer or older schema, or from another capture with one line naming the file."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import InputError
from .manifest import utc_now


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
    if got is None and "format" in doc:   # the self-description before odsplat.contract
        raise InputError(path, f"written by an older odsplat ({doc['format']!r} version {doc.get('version')!r}); "
                               "run its stage again")
    if got != kind:
        raise InputError(path, f"not an {kind} file (its kind is {got!r})")
    version = doc.get("schema_version")
    if isinstance(version, str):   # "1.0": the poses file before odsplat.contract
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
        raise InputError(path, f"belongs to another capture (id {other!r}, this capture is {capture_id!r}); "
                               "remove it or run its stage again")
    prov = doc.get("provenance") or {}
    if not isinstance(prov, dict):
        raise InputError(path, "provenance: expected an object")
    return Provenance(kind, version, str(other), prov.get("settings") or {}, prov.get("inputs") or {},
                      run_id=str(prov.get("run_id", "")), created_utc=str(prov.get("created_utc", "")))
