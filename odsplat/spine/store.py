"""The capture store: a directory with a manifest and one crash-safe HDF5 file per take (`Capture`).

Layout of a capture directory::

    capture.json          the manifest (odsplat.spine.manifest.Manifest)
    takes/<name>.h5       raw takes, written once: <name>.h5.partial while recording
    static/               optional photos of the still structure
    derived/              everything later stages write

A take file is written by `take_writer.TakeWriter`, read by `take_reader.TakeReader` (its layout is described
there and in docs/store.md), and recovered after a crash by `recovery.recover_partial`; files appear whole through
`atomic`.
"""
from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.contract import digest
from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.guard import lexically_inside, refuse_links
from odsplat.spine.manifest import ChannelInfo, Manifest, TakeRecord, check_name
from odsplat.spine.paths import DerivedPaths
from odsplat.spine.qcfile import read_verdicts
from odsplat.spine.recovery import RecoveryReport, recover_partial
from odsplat.spine.take_reader import TakeReader
from odsplat.spine.take_writer import PARTIAL_SUFFIX, TakeWriter

MANIFEST_NAME = "capture.json"
TAKE_SELECTIONS = ("accepted", "all")


class Capture:
    """A capture directory: the manifest, the raw takes and the derived results."""

    def __init__(self, root: str | Path, manifest: Manifest, derived: str | Path | None = None):
        self.root = Path(root)
        self.manifest = manifest
        # Every derived path comes from this registry; `derived` sends them elsewhere (the capture stays as it is).
        self.paths = DerivedPaths(Path(derived) if derived is not None else self.root / "derived")
        if derived is not None:
            self._check_derived_elsewhere(Path(derived))

    def _check_derived_elsewhere(self, derived: Path) -> None:
        """A derived folder given apart from the capture may lie anywhere but among its raw data (takes/, static/,
        the capture's own top folder) or above the capture: a stage's clean-up deletes files in it."""
        if lexically_inside(self.root, derived) and not lexically_inside(self.root / "derived", derived):
            parts = Path(os.path.relpath(os.path.abspath(derived), os.path.abspath(self.root))).parts
            raise InputError(derived, f"inside the capture's {parts[0] + '/' if parts else 'top folder'}; derived "
                                      "files go to derived/ or a folder outside the capture")
        if lexically_inside(derived, self.root):
            raise InputError(derived, f"holds the capture {self.root}; derived files go to a folder of their own")

    def refuse_links(self) -> None:
        """Refuse (one line) a capture that holds a symbolic link anywhere (capture.json, takes/, static/, derived/,
        or the derived folder given apart): odsplat goes through none (`guard`)."""
        outside = self.paths.root if not lexically_inside(self.root, self.paths.root) else None
        refuse_links(self.root)
        if outside is not None:
            refuse_links(outside)

    @classmethod
    def create(cls, root: str | Path, manifest: Manifest) -> Capture:
        root = Path(root)
        if (root / MANIFEST_NAME).exists():
            raise OdsplatError(f"{root}: a capture exists here already")
        manifest.validate(str(root / MANIFEST_NAME))
        if not manifest.capture_id:
            manifest.capture_id = uuid.uuid4().hex
        for sub in ("takes", "static", "derived"):
            (root / sub).mkdir(parents=True, exist_ok=True)
        capture = cls(root, manifest)
        capture.save_manifest()
        return capture

    @classmethod
    def open(cls, root: str | Path, *, derived: str | Path | None = None) -> Capture:
        """Open a capture; `derived` (a folder) takes every derived file instead of the capture's `derived/`."""
        root = Path(root)
        if not root.is_dir():
            raise InputError(root, "no such capture directory")
        capture = cls(root, Manifest.load(root / MANIFEST_NAME), derived)
        capture.refuse_links()
        return capture

    @property
    def id(self) -> str:
        """The capture's identity, recorded in every derived file: its manifest's id (older captures: a hash of
        their name and creation time)."""
        return self.manifest.capture_id or digest([self.manifest.name, self.manifest.created_utc])

    @property
    def takes_dir(self) -> Path:
        return self.root / "takes"

    @property
    def derived_dir(self) -> Path:
        """The root of the derived files (`paths.root`); reading it creates nothing."""
        return self.paths.root

    @property
    def static_dir(self) -> Path:
        return self.root / "static"

    def save_manifest(self) -> None:
        atomic_write_text(self.root / MANIFEST_NAME, self.manifest.to_json())

    # -- takes ------------------------------------------------------------------------------

    def take_names(self) -> list[str]:
        return [t.name for t in self.manifest.takes]

    def select_takes(self, which: str = "accepted") -> list[TakeRecord]:
        """The takes a stage works on, the one rule for every stage: the complete (or recovered) takes that QC
        accepted, or with "all" every complete take whatever its QC verdict."""
        if which not in TAKE_SELECTIONS:
            raise InputError("takes", f"expected one of {TAKE_SELECTIONS}, got {which!r}")
        complete = [t for t in self.manifest.takes if t.status in ("complete", "recovered")]
        if which == "all":
            return complete
        verdicts = self.qc_verdicts() if any(t.qc == "unchecked" for t in complete) else {}
        return [t for t in complete if (verdicts.get(t.name, "unchecked") if t.qc == "unchecked" else t.qc)
                == "accepted"]

    def unchecked_hint(self) -> str:
        """Why "accepted" may select nothing, for an error message: imported takes that qc has not judged yet."""
        waiting = [t.name for t in self.manifest.takes if t.status in ("complete", "recovered")
                   and t.qc == "unchecked" and t.name not in self.qc_verdicts()]
        return (f" ({len(waiting)} take(s) not checked yet: run `odsplat qc {self.root}` or `odsplat run`)"
                if waiting else "")

    def qc_verdicts(self) -> dict[str, str]:
        """The verdict the qc stage gave each take from its file (`derived/qc.json`), {} before it ran. A take
        recorded as unchecked (an imported one) is selected by this verdict; a recorded verdict stands. The file's
        format (and its one reader) is odsplat.spine.qcfile."""
        return read_verdicts(self.paths.qc_json, self.id)

    def next_take_name(self, view: int | None = None) -> str:
        stem = f"v{view:02d}" if view is not None else "take"
        existing = {p.name.split(".")[0] for p in self.takes_dir.iterdir()} if self.takes_dir.exists() else set()
        k = 0
        while f"{stem}_{k:03d}" in existing:
            k += 1
        return f"{stem}_{k:03d}"

    def new_take(
        self,
        name: str | None = None,
        *,
        view: int | None = None,
        frame_shape: Sequence[int] | None = None,
        dtype: Any = np.uint16,
        bit_depth: int | None = None,
        channels: Sequence[ChannelInfo] | None = None,
        fps: float | None = None,
        attrs: Mapping[str, Any] | None = None,
        daq_t0_s: float = 0.0,
    ) -> TakeWriter:
        """Start recording a take; the manifest lists it once `finalize()` succeeds."""
        name = check_name(name or self.next_take_name(view), f"{self.root}: take name")
        if name in self.take_names():
            raise OdsplatError(f"{self.root}: take {name!r} exists already; raw takes are written once")
        channels = self.manifest.channels if channels is None else channels
        all_attrs = {"view": -1 if view is None else view, "fps": np.nan if fps is None else fps,
                     "capture": self.manifest.name}
        all_attrs.update(attrs or {})
        return TakeWriter(
            self.takes_dir / f"{name}.h5",
            frame_shape=frame_shape,
            dtype=dtype,
            bit_depth=bit_depth,
            channels=channels,
            daq_sample_rate_hz=self.manifest.daq_sample_rate_hz,
            daq_t0_s=daq_t0_s,
            attrs=all_attrs,
            on_finalize=self._register,
        )

    def _register(self, record: TakeRecord) -> None:
        self.manifest.takes = [t for t in self.manifest.takes if t.name != record.name] + [record]
        self.save_manifest()

    def open_take(self, name: str) -> TakeReader:
        for t in self.manifest.takes:
            if t.name == name:
                return TakeReader(self.root / t.file)
        raise InputError(self.root, f"no take {name!r}; the capture has {self.take_names()}")

    def partial_takes(self) -> list[Path]:
        """Unfinished take files left by a writer that stopped before finalising."""
        return sorted(self.takes_dir.glob("*" + PARTIAL_SUFFIX)) if self.takes_dir.exists() else []

    def unlisted_takes(self) -> list[Path]:
        """Finalised take files the manifest does not list (a crash between rename and manifest write)."""
        listed = {t.file for t in self.manifest.takes}
        return [p for p in sorted(self.takes_dir.glob("*.h5")) if f"takes/{p.name}" not in listed]

    def recover(self) -> list[RecoveryReport]:
        """Recover every unfinished take and list finalised takes the manifest missed."""
        reports = []
        for partial in self.partial_takes():
            report = recover_partial(partial)
            reports.append(report)
        for path in self.unlisted_takes():
            with TakeReader(path) as reader:
                record = TakeRecord(
                    name=path.name[:-3],
                    file=f"takes/{path.name}",
                    view=reader.view,
                    status="recovered" if reader.recovered else "complete",
                    qc=reader.qc.status,
                    n_frames=reader.n_frames,
                    n_samples=reader.n_samples,
                    created_utc=str(reader.attrs.get("created_utc", "")),
                )
            self._register(record)
        return reports

    def copy_static(self, files: Sequence[Path]) -> None:
        self.static_dir.mkdir(exist_ok=True)
        for src in files:
            shutil.copy2(src, self.static_dir / Path(src).name)
