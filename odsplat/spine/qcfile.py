"""The qc stage's file, `derived/qc.json`: each take's verdicts and the settings that gave them. Its one reader and
writer: the acquisition stage's `QCReport` writes and reads it, the store's `Capture.qc_verdicts` selects imported
(unchecked) takes by it. The file opens with the provenance header every derived file has (`contract`)."""
from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.contract import check, describe
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import QC_STATUSES, from_plain, load_json
from odsplat.spine.paths import DerivedPaths

KIND = "odsplat.qc"
SCHEMA = 2   # 2: the settings' `impacts` (odsplat.spine.impulse.ImpactSettings) replace `double_hit_fraction`
VERDICTS = ("accepted", "rejected")   # what the qc stage finds in a take's file
MISSING = "no QC result (run `odsplat run CAPTURE --to qc` first)"


@dataclass(frozen=True)
class TakeQC:
    """One take's verdicts: the one recorded with it (at capture or import) and the one from its file now."""

    name: str
    recorded: str                  # the manifest's: accepted, rejected or unchecked
    checked: str                   # from the file: accepted or rejected
    reasons: tuple[str, ...]
    details: tuple[str, ...]
    peak_force_n: float | None
    n_impacts: int
    content: str = ""              # what the take holds: frames, force, response, joined by "+" ("" in older files)

    @property
    def status(self) -> str:
        """The verdict that stands: the recorded one, or the check's where none was recorded."""
        return self.checked if self.recorded == "unchecked" else self.recorded


@dataclass(frozen=True)
class QCFile:
    """The contents of `derived/qc.json`: every complete take's verdicts, and the qc stage's settings as plain data
    (JSON-like; the acquisition stage turns them back into its `QCSettings`)."""

    takes: tuple[TakeQC, ...]
    settings: Mapping[str, Any] = field(default_factory=dict)

    def verdicts(self) -> dict[str, str]:
        """Each take's verdict from its file (`checked`), by name."""
        return {t.name: t.checked for t in self.takes}

    def write(self, path: Path, capture_id: str) -> None:
        """Write the file (atomically), with its header: kind, schema, the capture's id and the settings."""
        prov = describe(capture_id, KIND, SCHEMA, dict(self.settings))
        doc = {**prov.header(), "takes": [{**asdict(t), "status": t.status} for t in self.takes]}
        DerivedPaths.ensure(path.parent)
        atomic_write_text(path, json.dumps(doc, indent=1, allow_nan=False, default=str) + "\n")

    @classmethod
    def read(cls, path: Path, capture_id: str | None, *, missing: str = MISSING) -> QCFile:
        """Read and check the file: its kind, schema and capture (`capture_id`; None: any), and every take's
        fields. One line naming the file (and the take) when anything is wrong; `missing` says what was expected
        where there is no file."""
        doc = load_json(path, missing=missing)
        prov = check(doc, path, kind=KIND, schema_version=SCHEMA, capture_id=capture_id)
        if not isinstance(prov.settings, dict):
            raise InputError(f"{path}: settings", f"expected an object; got {type(prov.settings).__name__}")
        raw = doc.get("takes")
        if not isinstance(raw, list):
            raise InputError(path, f"takes: expected a list of takes; got {type(raw).__name__}")
        takes = []
        for i, t in enumerate(raw):
            where = f"{path}: takes[{i}]"
            t = {k: v for k, v in t.items() if k != "status"} if isinstance(t, dict) else t  # status is derived
            take = from_plain(TakeQC, t, where)
            if take.checked not in VERDICTS:
                raise InputError(f"{where}.checked", f"expected one of {', '.join(VERDICTS)}; got {take.checked!r}")
            if take.recorded not in QC_STATUSES:
                raise InputError(f"{where}.recorded",
                                 f"expected one of {', '.join(QC_STATUSES)}; got {take.recorded!r}")
            takes.append(take)
        return cls(tuple(takes), prov.settings)


def read_verdicts(path: Path, capture_id: str | None) -> dict[str, str]:
    """Each take's verdict from its file, by name (`QCFile.verdicts`); {} where the qc stage has not run."""
    if not path.is_file():
        return {}
    return QCFile.read(path, capture_id, missing="no QC result").verdicts()


__all__ = ["KIND", "SCHEMA", "VERDICTS", "QCFile", "TakeQC", "read_verdicts"]
