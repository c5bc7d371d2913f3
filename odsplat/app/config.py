"""The pipeline's configuration: every stage's settings, from the documented defaults, the capture's optional
`odsplat.toml` and the command line's overrides, in that order (docs/config.md)."""
from __future__ import annotations

import dataclasses
import textwrap
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tomli_w

from odsplat.app.budget import RunSettings
from odsplat.app.stages import STAGES
from odsplat.app.stages import stage as stage_record
from odsplat.spine.checks import shown
from odsplat.spine.contract import plain
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import MAX_TOML_DEPTH, from_plain, load_toml, parse_toml_value

CONFIG_NAME = "odsplat.toml"
_WITH_SETTINGS = tuple(name for name in STAGES if stage_record(name).settings_path is not None)
MAX_SET_CHARS = 10_000          # one --set: a list of a thousand frequencies fits
RUN = "run"                     # the section of the run's own settings (budget.py), beside the stages'


def settings_types() -> dict[str, type]:
    """Each stage's settings class, from the stage table (each imported now: some load torch)."""
    return {name: settings_type(name) for name in _WITH_SETTINGS}


def settings_type(name: str) -> type:
    """One stage's settings class, imported now (and only that stage)."""
    cls = stage_record(name).settings_class
    if cls is None:
        raise InputError("stage", f"{name} has no settings; expected one of {', '.join(_WITH_SETTINGS)}")
    return cls


@dataclass(frozen=True)
class Config:
    """Every stage's settings. They are built from `table`, the layers laid over each other (defaults, then the
    file, then the command line), so a setting left out stays automatic: a stage derives it from the others (the
    reconstruction's frames from its motion model, say). `given` holds settings objects handed over whole."""

    table: dict[str, Any] = field(default_factory=dict)
    sources: tuple[str, ...] = ("defaults",)
    given: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def defaults(cls) -> Config:
        return cls()

    def settings(self, stage: str) -> Any:
        if stage == RUN:
            return from_plain(RunSettings, self.table.get(RUN, {}), f"{', '.join(self.sources)}: {RUN}")
        if stage not in _WITH_SETTINGS:
            raise InputError("stage", f"expected one of {', '.join(STAGES)}; got {stage!r}")
        if stage in self.given:
            return self.given[stage]
        table = self.table.get(stage, {})
        if stage == "magnify" and "views" not in table and "every_view" not in table \
                and self.reconstruct.source != "sync":
            # a reconstruction from magnified frames reads every view's: magnify them all (else only one, to watch)
            table = {**table, "every_view": True}
        return from_plain(settings_type(stage), table, f"{', '.join(self.sources)}: {stage}")

    qc = property(lambda self: self.settings("qc"))
    sync = property(lambda self: self.settings("sync"))
    magnify = property(lambda self: self.settings("magnify"))
    poses = property(lambda self: self.settings("poses"))
    reconstruct = property(lambda self: self.settings("reconstruct"))
    analyze = property(lambda self: self.settings("analyze"))
    report = property(lambda self: self.settings("report"))
    run = property(lambda self: self.settings(RUN))

    def replace(self, stage: str, settings: Any) -> Config:
        """These settings, with one stage's replaced by a settings object."""
        self.settings(stage)  # checks the name
        return dataclasses.replace(self, given={**self.given, stage: settings})

    def updated(self, table: dict[str, Any], source: str) -> Config:
        """These settings with a table laid over them: {stage: {field: value, sub: {field: value}}}. Each stage it
        touches is built at once, so a bad value is named with the layer that brought it."""
        if not isinstance(table, dict):
            raise InputError(source, "expected a table of stages")
        unknown = sorted(set(table) - set(_WITH_SETTINGS) - {RUN})
        if unknown:
            raise InputError(source, f"unknown stage(s) {shown(unknown)}; expected some of "
                                     f"{[*_WITH_SETTINGS, RUN]}")
        for stage, over in table.items():
            if not isinstance(over, dict):
                raise InputError(f"{source}: [{stage}]", "expected a table of settings")
        merged = _merge(self.table, table)
        for stage in table:
            from_plain(RunSettings if stage == RUN else settings_type(stage), merged[stage], f"{source}: {stage}")
        given = {k: v for k, v in self.given.items() if k not in table}
        return Config(merged, (*self.sources, source), given)

    def to_dict(self) -> dict[str, Any]:
        return {stage: plain(self.settings(stage)) for stage in (*_WITH_SETTINGS, RUN)}

    def to_toml(self) -> str:
        """The effective configuration as an `odsplat.toml` (settings left automatic, None, as comments)."""
        unset: list[str] = []
        table = {stage: _drop_none(d, stage, unset) for stage, d in self.to_dict().items()}
        head = [f"# odsplat configuration; from: {', '.join(self.sources)}"]
        if unset:
            head += textwrap.wrap("automatic (unset): " + ", ".join(unset), 116, initial_indent="# ",
                                  subsequent_indent="#   ")
        return "\n".join(head) + "\n\n" + tomli_w.dumps(table)


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def _drop_none(d: dict[str, Any], where: str, unset: list[str]) -> dict[str, Any]:
    out = {}
    for key, value in d.items():
        if value is None:
            unset.append(f"{where}.{key}")
        elif isinstance(value, dict):
            out[key] = _drop_none(value, f"{where}.{key}", unset)
        else:
            out[key] = value
    return out


def parse_set(item: str) -> dict[str, Any]:
    """`stage.field=value` (or `stage.sub.field=value`) as a nested table; the value is read as TOML, else kept
    as a string: `magnify.alpha=30`, `analyze.fmax_hz=900`, `magnify.band_hz=[20, 400]`."""
    if len(item) > MAX_SET_CHARS:
        raise InputError("--set", f"expected STAGE.FIELD=VALUE of at most {MAX_SET_CHARS} characters; got "
                                  f"{len(item)}, starting {shown(item[:40])}")
    key, eq, text = item.partition("=")
    parts = key.strip().split(".")
    if not eq or len(parts) < 2 or not all(p.isidentifier() for p in parts):
        raise InputError("--set", f"expected STAGE.FIELD=VALUE, e.g. magnify.alpha=30; got {shown(item)}")
    if len(parts) > MAX_TOML_DEPTH:
        raise InputError("--set", f"{shown(key)} is nested too deep: more than {MAX_TOML_DEPTH} names")
    try:
        value = parse_toml_value(text.strip(), f"--set {key.strip()}")
    except tomllib.TOMLDecodeError:
        value = text.strip()
    table: dict[str, Any] = {parts[-1]: value}
    for p in reversed(parts[:-1]):
        table = {p: table}
    return table


def load_config(capture: Any = None, *, path: str | Path | None = None, sets: tuple[str, ...] = ()) -> Config:
    """The effective configuration: defaults, then `path` (default: the capture's odsplat.toml when it has one),
    then each `--set STAGE.FIELD=VALUE`."""
    config = Config.defaults()
    if path is None and capture is not None:
        candidate = Path(capture.root) / CONFIG_NAME
        path = candidate if candidate.exists() else None
    if path is not None:
        config = config.updated(load_toml(path, missing="no such configuration file"), str(path))
    for item in sets:
        # The layer is named by the item itself, cut short where a hostile one runs to thousands of characters.
        layer = item if len(item) <= 120 else f"{item[:100]}... ({len(item)} characters)"
        config = config.updated(parse_set(item), f"--set {layer}")
    return config


__all__ = ["CONFIG_NAME", "STAGES", "Config", "load_config", "parse_set", "settings_type", "settings_types"]
