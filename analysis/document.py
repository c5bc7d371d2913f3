"""analysis.json as one typed, versioned record, `AnalysisDocument`: what the analysis writes and what the report, the
viewer and the demo read. `to_json`/`from_json` are the one translation between it and the file's JSON, and
`from_json` checks every field: a missing field, or a hand-edited one of the wrong kind, is refused in one line
naming it ("analysis.json: video.noise_floor.sigma_um: expected a number; got 'abc'").

Every section is a frozen dataclass whose field names are the file's keys, in the file's order; the types say what
each holds (`float | None`: a number or null). A field with a default may be absent from the file (a section the
analysis did not compute, or a field older files of this schema lack); one marked `_omitted()` is left out of the
file where it is None or empty, as the analysis has always left it."""
from __future__ import annotations

import dataclasses
import functools
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.checks import MAX_LENGTH_M, shown
from odsplat.spine.contract import Provenance, check, plain
from odsplat.spine.errors import InputError
from odsplat.spine.manifest import load_json
from odsplat.spine.store import Capture

from .crosscheck import ViewCheck
from .verdict import BELOW_FLOOR, NOT_SEPARATED, ModeStatus, Verdict

KIND = "odsplat.analysis"
SCHEMA = 3              # 3: the correlation's reference AutoMAC, the video's full-field cross-MAC, per-mode statuses,
#                          the video's physical limit (Cramér-Rao bound)
READABLE_SCHEMAS = (2, 3)   # a schema 2 file reads with those absent (None)


def _omitted(default: Any = None) -> Any:
    """A field left out of the file where it holds `default` (None, or an empty tuple), and absent there read so."""
    return field(default=default, metadata={"omit": True})


# ---------------------------------------------------------------------------------------------- the sections

@dataclass(frozen=True)
class ModeEntry:
    """An accelerometer mode."""

    freq_hz: float
    damping: float          # fraction of critical


@dataclass(frozen=True)
class RejectedHit:
    take: str
    reasons: tuple[str, ...]


@dataclass(frozen=True)
class NoiseModeEntry:
    """One mode's amplitude at the sensors against the video's noise floor there (micrometres)."""

    freq_hz: float
    amplitude_um: float
    floor_um: float
    spectrum_gain: float    # the noise's level at the mode over its mean
    below_floor: bool
    separation_gain: float | None = _omitted()   # its fit's gain over its gain alone (noise.separation_gains)
    not_separated: bool | None = _omitted()      # above the floor, not separated by the record: not judged
    record_needed_s: float | None = _omitted()   # the record that would separate it (None: this one does, or none)
    full_field_mac: float | None = _omitted()    # the MAC the noise allows its shape over the whole structure
    below_at_sensors: bool | None = _omitted()   # below the floor at the sensors (below_floor: there or overall)


@dataclass(frozen=True, kw_only=True)
class NoiseFloorSection:
    """The video's noise floor (analysis/noise.py), micrometres."""

    sigma_um: float                          # per point and timestep, the median over the points
    static_sigma_um: float | None            # on the points the modes explain none of (None: none)
    n_static_points: int
    pre_impact_sigma_um: float | None        # before the impact (None: too few timesteps there)
    n_pre_impact: int
    sensor_sigma_um: tuple[float, ...]
    point_sigma_um_p10_p90: tuple[float, float]
    floor_sigmas: float                      # noise standard deviations a mode needs to be judged
    floor_mac: float | None = None           # the MAC the noise allows a shape at the floor (older files lack it)
    modes: tuple[NoiseModeEntry, ...]


@dataclass(frozen=True)
class RealModeEntry:
    """One video mode's shape as a real mode (analysis/noise.py: real_modes)."""

    freq_hz: float
    mpc: float
    quadrature_over_noise: float
    lost: float
    real: bool


@dataclass(frozen=True, kw_only=True)
class VideoSection:
    """The video side: the modes fitted to the reconstruction's motion with the accelerometer poles."""

    modes_fitted: tuple[int, ...]            # their index in `modes`
    sensor_r2: tuple[float, ...]
    condition: float
    freq_hz: tuple[float, ...]               # the video's own poles
    damping: tuple[float, ...]
    window_s: tuple[float, float]
    n_surface_points: int
    shapes_from: str                         # "trajectories" or "measured"
    # the background, left out of the shapes (older files of this schema lack these)
    n_background_points: int = 0
    structure_rule: str = ""
    background_rms_um: float | None = None
    background_amplitude_um: float | None = None
    background_amplitude_ratio: float | None = None
    background_amplitude_ratio_all: float | None = None
    n_background_reference_points: int = 0
    crosscheck: tuple[ViewCheck, ...]        # the 2D cross-check, per view
    noise_floor: NoiseFloorSection | None = _omitted()
    real_modes: tuple[RealModeEntry, ...] | None = _omitted()
    crosscheck_verdict: Verdict | None = _omitted()
    crosscheck_gain_median: float | None = _omitted()
    crosscheck_correlation_median: float | None = _omitted()
    # the camera's Cramér-Rao bound against the measured floor, per point and mode, and each mode's motion below
    # the floor per direction (analysis/crlb.py `physical_limit`; micrometres)
    physical_limit: dict[str, Any] | None = _omitted()
    # several views' 2D tracks triangulated to 3D against the Gaussians' motion and shapes (triangulate.py)
    triangulation: dict[str, Any] | None = _omitted()


@dataclass(frozen=True, kw_only=True)
class ImagePolesSection:
    """Poles from the synced takes' raw frames (analysis/imagepoles.py)."""

    freq_hz: tuple[float, ...]
    damping: tuple[float, ...]
    n_views: int
    n_pixels: int
    window_s: tuple[float, float]
    component_snr: tuple[float, ...]


@dataclass(frozen=True, kw_only=True)
class PairEntry:
    """An accelerometer mode (a) paired with a video mode (b): both index the video's fitted modes
    (`VideoSection.modes_fitted`)."""

    a: int
    b: int
    mac: float
    scale_factor_abs: float
    scale_factor_phase_deg: float
    freq_a_hz: float | None = None
    freq_b_hz: float | None = None
    freq_diff_rel: float | None = None
    # against the video's noise floor, where it has one
    video_amplitude_um: float | None = _omitted()
    noise_floor_um: float | None = _omitted()
    below_noise_floor: bool | None = _omitted()
    expected_mac: float | None = _omitted()


@dataclass(frozen=True, kw_only=True)
class CorrelationSection:
    """The video's shapes against the accelerometers'."""

    pairs: tuple[PairEntry, ...]
    comac: tuple[float, ...]                 # per sensor
    verdict: Verdict | None = _omitted()     # the MAC target over the modes above the noise floor, and per mode
    # (schema 3) indexed as the pairs: the MAC matrix, the accelerometer shapes' AutoMAC at the sensors, and the
    # video's shapes' cross-MAC over every surface point (None: no surface)
    mac_matrix: tuple[tuple[float, ...], ...] | None = _omitted()          # a (rows) against b (columns)
    reference_automac: tuple[tuple[float, ...], ...] | None = _omitted()
    video_cross_mac: tuple[tuple[float, ...], ...] | None = _omitted()


@dataclass(frozen=True)
class OdsEntry:
    """An ODS line: the video's ODS against the accelerometers' there."""

    freq_hz: float
    mac: float


@dataclass(frozen=True, kw_only=True)
class AnalysisDocument:
    """analysis.json: the header every derived file opens with (`provenance`), then the analysis's key numbers."""

    provenance: Provenance = field(metadata={"header": True})
    capture: str                             # the capture's folder name
    created_utc: str
    settings: dict[str, Any]                 # AnalyzeSettings as plain data
    takes: tuple[str, ...]
    n_averages: int
    rejected_hits: tuple[RejectedHit, ...]
    sensors: tuple[str, ...]
    exp_tau_s: float | None
    modes: tuple[ModeEntry, ...]
    band_hz: tuple[float, float]
    notes: tuple[str, ...]                   # analysis/notes.py words them
    video: VideoSection | None = _omitted()
    image_poles: ImagePolesSection | None = _omitted()
    correlation: CorrelationSection | None = _omitted()
    ods: tuple[OdsEntry, ...] = _omitted(())
    # without a 3D video side: the accelerometers one view sees against its 2D tracks (sensorview.SensorView)
    sensor_view: dict[str, Any] | None = _omitted()
    files: dict[str, str]                    # what -> file name in derived/analysis/

    # ------------------------------------------------------------------------------------------ the file

    def to_json(self) -> dict[str, Any]:
        """The file's JSON object: the header, then every field in order."""
        return {**self.provenance.header(), **_plain(AnalysisDocument, self)}

    @classmethod
    def from_json(cls, doc: Any, path: str | Path, *, capture_id: str | None = None) -> AnalysisDocument:
        """The document in `doc` (parsed JSON) read from `path`: its header checked (kind, schema, and the capture
        where `capture_id` is given), then every field; InputError naming the first field that is wrong."""
        version = doc.get("schema_version") if isinstance(doc, dict) else None
        older = type(version) is int and version in READABLE_SCHEMAS
        provenance = check(doc, path, kind=KIND, schema_version=version if older else SCHEMA, capture_id=capture_id)
        reader = _Reader(str(path))
        out = reader.fields(cls, doc, "", provenance=provenance)
        reader.check_structure_settings(out.settings)
        return out

    @classmethod
    def read(cls, capture: Capture) -> AnalysisDocument:
        """The capture's derived/analysis/analysis.json, checked."""
        path = capture.paths.analysis_json
        return cls.from_json(load_json(path, missing="no analysis (run `odsplat analyze` first)"), path,
                             capture_id=capture.id)

    def write(self, capture: Capture) -> Path:
        """Writes it as the capture's analysis.json (atomically); returns the path."""
        path = capture.paths.analysis_json
        atomic_write_text(path, json.dumps(self.to_json(), indent=1))
        return path

    # ------------------------------------------------------------------------------------------ readings

    def settings_text(self) -> str:
        """The settings the analysis ran with, as the file holds them (indented JSON)."""
        return json.dumps(self.settings, indent=1)

    def structure_settings(self) -> dict[str, Any]:
        """The analysis's own structure rule where it saved it (from_json checked both): floor_margin_m and
        structure_box_m, as keyword arguments of AnalyzeSettings."""
        kw: dict[str, Any] = {}
        if "floor_margin_m" in self.settings:
            kw["floor_margin_m"] = self.settings["floor_margin_m"]
        if self.settings.get("structure_box_m") is not None:
            kw["structure_box_m"] = tuple(tuple(float(x) for x in c) for c in self.settings["structure_box_m"])
        return kw

    def pair_by_mode(self) -> dict[int, PairEntry]:
        """Each accelerometer mode's correlation pair, by the mode's index in `modes`: a pair's b is the video's
        fitted mode, which `video.modes_fitted` maps to the accelerometer mode. A pair that names no mode (a
        hand-edited index) is left out."""
        fitted = self.video.modes_fitted if self.video is not None else ()
        out = {}
        for p in self.correlation.pairs if self.correlation is not None else ():
            if 0 <= p.b < len(fitted) and 0 <= fitted[p.b] < len(self.modes):
                out[fitted[p.b]] = p
        return out

    def not_judged(self) -> dict[int, str]:
        """Why each mode the video's verdict did not judge was not (by its index in `modes`): below the noise floor
        (its pair's flag, or its status), or not separated from a mode beside it. The report's table and the
        viewer's list grey these modes and say so."""
        out = {k: NOT_JUDGED_BELOW for k, p in self.pair_by_mode().items() if p.below_noise_floor}
        verdict = self.correlation.verdict if self.correlation is not None else None
        for st in verdict.modes if verdict is not None else ():
            k = st.mode - 1
            if 0 <= k < len(self.modes) and k not in out:
                if st.status == BELOW_FLOOR:
                    out[k] = NOT_JUDGED_BELOW
                elif st.status == NOT_SEPARATED:
                    out[k] = NOT_JUDGED_APART
        return out


NOT_JUDGED_BELOW = "below the noise floor: not judged"
NOT_JUDGED_APART = "not separated from a mode beside it: not judged"


def read_analysis(capture: Capture) -> AnalysisDocument:
    """The capture's analysis.json (`AnalysisDocument.read`): every field checked, one line naming a wrong one."""
    return AnalysisDocument.read(capture)


# ---------------------------------------------------------------------------------------------- plain JSON

@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _optional(tp: Any) -> Any | None:
    """T for `T | None`, else None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return args[0] if len(args) == 1 else None
    return None


def _plain(tp: Any, value: Any) -> Any:
    """value, declared as tp, as JSON data (numbers made Python's own by their declared kind)."""
    if value is None:
        return None
    inner = _optional(tp)
    if inner is not None:
        return _plain(inner, value)
    if tp is Verdict:
        return plain(value.summary())
    if dataclasses.is_dataclass(tp):
        hints = _hints(tp)
        return {f.name: _plain(hints[f.name], getattr(value, f.name)) for f in dataclasses.fields(tp)
                if not f.metadata.get("header")
                and not (f.metadata.get("omit") and getattr(value, f.name) in (None, ()))}
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple:
        kinds = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        return [_plain(k, v) for k, v in zip(kinds, value)]
    if origin is dict:
        return {str(k): _plain(args[1], v) for k, v in value.items()} if args[1] is not Any else plain(value)
    if tp in (float, int, bool, str):
        return tp(value)
    return value


# ---------------------------------------------------------------------------------------------- checked reading

_NAMES = {float: "a number", int: "an integer", bool: "true or false", str: "a string"}


class _Reader:
    """Reads JSON data into the declared types, naming each field by its path in the file in any error."""

    def __init__(self, path: str):
        self.path = path

    def fail(self, where: str, problem: str) -> InputError:
        return InputError(f"{self.path}: {where}" if where else self.path, problem)

    def _expected(self, tp: Any, value: Any, where: str) -> InputError:
        name = _NAMES.get(tp) or ("a list" if typing.get_origin(tp) is tuple else "an object")
        return self.fail(where, f"expected {name}; got {shown(value)}")

    def read(self, tp: Any, value: Any, where: str) -> Any:
        inner = _optional(tp)
        if inner is not None:
            return None if value is None else self.read(inner, value, where)
        if tp is Verdict:
            return self._verdict(value, where)
        if dataclasses.is_dataclass(tp):
            return self.fields(tp, value, where)
        origin, args = typing.get_origin(tp), typing.get_args(tp)
        if origin is tuple:
            if not isinstance(value, list):
                raise self._expected(tp, value, where)
            if len(args) == 2 and args[1] is Ellipsis:
                return tuple(self.read(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
            if len(value) != len(args):
                raise self.fail(where, f"expected a list of {len(args)} values; got {len(value)}")
            return tuple(self.read(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        if origin is dict:
            if not isinstance(value, dict):
                raise self._expected(tp, value, where)
            if args[1] is Any:
                return value
            return {k: self.read(args[1], v, _key(where, k)) for k, v in value.items()}
        return self._scalar(tp, value, where)

    def _scalar(self, tp: Any, value: Any, where: str) -> Any:
        if tp is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise self._expected(tp, value, where)
            try:
                return float(value)
            except OverflowError:            # an integer beyond a float's range
                raise self.fail(where, f"expected a number; got {shown(value)}") from None
        if tp is int and (isinstance(value, bool) or not isinstance(value, int)):
            raise self._expected(tp, value, where)
        if tp in (bool, str) and not isinstance(value, tp):
            raise self._expected(tp, value, where)
        return value

    def _object(self, value: Any, where: str) -> dict:
        if not isinstance(value, dict):
            raise self.fail(where, f"expected an object; got {shown(value)}")
        return value

    def fields(self, cls: type, value: Any, where: str, **given: Any) -> Any:
        """Dataclass `cls` from the object `value`, field by field (those `given` as they are); a key it does not
        declare is left unread."""
        d = self._object(value, where)
        hints = _hints(cls)
        kwargs = dict(given)
        for f in dataclasses.fields(cls):
            at = f"{where}.{f.name}" if where else f.name
            if f.name in given:
                continue
            if f.name in d:
                kwargs[f.name] = self.read(hints[f.name], d[f.name], at)
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise self.fail(at, "missing")
        return cls(**kwargs)

    def _verdict(self, value: Any, where: str) -> Verdict:
        """A verdict: its status and line, and its numbers (details) as the file holds them."""
        d = self._object(value, where)
        for key in ("status", "line"):
            if key not in d:
                raise self.fail(f"{where}.{key}", "missing")
            self._scalar(str, d[key], f"{where}.{key}")
        modes = self.read(tuple[ModeStatus, ...], d["modes"], f"{where}.modes") if "modes" in d else ()
        return Verdict(d["status"], d["line"], {k: v for k, v in d.items() if k not in ("status", "line", "modes")},
                       modes)

    def check_structure_settings(self, settings: dict[str, Any]) -> None:
        """The two settings the viewer reads back (the analysis's structure rule): a margin in metres, or null; a
        box of two corners [x, y, z] in metres, or null."""
        margin = settings.get("floor_margin_m")
        if margin is not None:
            self._scalar(float, margin, "settings.floor_margin_m")
        box = settings.get("structure_box_m")
        if box is not None:
            self.read(tuple[tuple[float, float, float], tuple[float, float, float]], box, "settings.structure_box_m")
            if any(abs(x) > MAX_LENGTH_M for c in box for x in c):
                raise self.fail("settings.structure_box_m", f"expected corners within +-{MAX_LENGTH_M:g} m; got "
                                                            f"{shown(box)}")


def _key(where: str, key: str) -> str:
    """An object's entry in an error's field path: `files.frf`, or `files['a b']` where the key is no plain name."""
    return f"{where}.{key}" if key.isidentifier() else f"{where}[{shown(key)}]"


__all__ = ["KIND", "READABLE_SCHEMAS", "SCHEMA", "AnalysisDocument", "CorrelationSection", "ImagePolesSection",
           "ModeEntry", "NoiseFloorSection", "NoiseModeEntry", "OdsEntry", "PairEntry", "RealModeEntry", "RejectedHit",
           "VideoSection", "read_analysis"]
