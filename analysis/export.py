"""Export of test results (geometry, time series, FRFs, mode shapes and ODS) to universal files (UFF) and to a
documented HDF5 layout, and back, through plain records that do not depend on how the analysis made them.

UFF (`write_uff` / `read_uff`, through pyuff): 151 header and 164 units (SI: metre, newton, second), 2411 nodes
(metres), 82 trace lines, 58 functions (function type 1 time response, 4 FRF, 6 coherence; double precision,
complex FRFs, real coherence), 55 shapes (3-DOF translation vectors; real modes as analysis type 2 with frequency
and viscous damping ratio, complex modes as type 3 with the eigenvalue -zeta*wn + i*wn*sqrt(1-zeta^2) in rad/s,
ODS as type 5 at a frequency line). Headers hold 6 significant digits (E13.5): abscissa start and step,
frequencies, dampings and all of dataset 55; ordinates of 58 hold 12. ID line 1 is the record's name; an
`odsplat ... unit=U set=S` tag in ID line 4 of a 55 keeps its unit and shape set, and a direction given as a
vector is kept in ID line 5 (`rsp=(x,y,z)`). A 55's shape set is its load case (1, 2, ... in the order the sets
first appear), its number the mode number (modes) or frequency step number (ODS), counted within its set and
kind unless the record gives one: two sets may each hold a mode 3 (the same pole seen by two instruments).

HDF5 layout (`write_results_h5` / `read_results_h5`), groups kept in the order written::

    /                      attrs kind="odsplat.results", schema_version=3, created_utc, json_attrs (the
                           names of the user attrs stored as JSON text), capture_id (the capture's, when
                           written for one; `read_results_h5` given the capture refuses another's), then the
                           user attrs
    /geometry              node_ids (P,) int64, coords_m (P,3) float64 [attr unit="m"],
                           lines (L,2) int64 (when given), names (P,) utf-8 (when given)
    /time_series/<name>    values (N,) float64; attrs node_id, direction, quantity, unit, t0_s, dt_s
    /frfs/<name>           freq_hz (F,) float64, values (F,) complex128; attrs response_node,
                           response_direction, reference_node, reference_direction, quantity, unit
    /coherence/<name>      freq_hz (F,) float64, values (F,) float64 in [0, 1]; attrs response_node,
                           response_direction, reference_node, reference_direction
    /shapes/<name>         node_ids (P,) int64, values (P,3) complex128 (X, Y, Z); attrs freq_hz, damping,
                           kind ("mode"|"ods"), unit, number (0: by order), shape_set
    /mac/<name>            mac (A,B) float64, modes_a (A,) int64, modes_b (B,) int64, pairs (K,2) int64 (row,
                           column), pair_mac (K,), scale_factor (K,) complex128 (a ~ s b), pair_freq_a_hz,
                           pair_freq_b_hz (K,) float64 (NaN: not found), comac (D,) float64, comac_nodes (D,)
                           int64; attrs label_a, label_b
    /stabilisation/<name>  order (P,) int64, poles_rad_s (P,) complex128, status (P,) utf-8 ("stable", "damping",
                           "freq", "new"), selected_rad_s (M,) complex128; attrs freq_tol, damping_tol,
                           window_tau_s (the poles are as fitted, with the exponential window's 1/tau)

Every numeric array with elements is stored with a Fletcher-32 checksum per chunk: a damaged file reads as an
error naming it, never as other numbers. A direction attr is a string ("+X", "-Z", "scalar", ...) or a float64 unit
vector (3,). Schema 3 added coherence, mac, stabilisation and the shapes' number and shape_set; schema 2 files read
with their defaults.
"""
from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Sequence
from dataclasses import MISSING, dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pyuff

from odsplat.spine.contract import CAPTURE_KEY, check_capture
from odsplat.spine.errors import InputError, OdsplatError, SchemaError
from odsplat.spine.space import writing_h5
from odsplat.spine.store import atomic_path

log = logging.getLogger(__name__)

RESULTS_KIND = "odsplat.results"
RESULTS_SCHEMA = 3
READABLE_SCHEMAS = (2, 3)
# UFF direction codes (58 record 6): 1..3 translations, 4..6 rotations, 0 scalar.
_DIR_CODE = {"scalar": 0, **{f"{s}{a}": (1 if s == "+" else -1) * (i + 1) for s in "+-"
                             for i, a in enumerate(("X", "Y", "Z", "RX", "RY", "RZ"))}}
_CODE_DIR = {v: k for k, v in _DIR_CODE.items()}
# quantity -> (UFF specific data type, axis label, SI unit)
_QUANTITY = {"displacement": (8, "Displacement", "m"), "velocity": (11, "Velocity", "m/s"),
             "acceleration": (12, "Acceleration", "m/s^2"), "force": (13, "Force", "N"),
             "pressure": (15, "Pressure", "Pa"), "unknown": (0, "NONE", "")}
_SPEC_QUANTITY = {8: "displacement", 11: "velocity", 12: "acceleration", 13: "force", 9: "force",
                  15: "pressure", 21: "pressure"}  # 21: Test.Lab's sound pressure
_FRF_NUMERATOR = {"receptance": "displacement", "mobility": "velocity", "accelerance": "acceleration",
                  "unknown": "unknown"}
_MONTHS = ("Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec")
_VECTOR_TAG = re.compile(r"\b(rsp|ref)=\(([^)]*)\)")
_UNIT_TAG = re.compile(r"\bodsplat\b.*\bunit=(\S+)")
_SET_TAG = re.compile(r"\bodsplat\b.*\bset=(\S+)")
_STATUSES = ("stable", "damping", "freq", "new")

Direction = str | tuple[float, float, float]


# ------------------------------------------------------------------------------------------ validation helpers

def _direction(value: Any, source: str, fld: str) -> Direction:
    """A canonical direction: "+X".."-RZ" or "scalar", or a unit 3-vector (tuple)."""
    if isinstance(value, str):
        s = value.strip().upper()
        s = "scalar" if s == "SCALAR" else ("+" + s if s and s[0] not in "+-" else s)
        if s in _DIR_CODE:
            return s
        raise InputError(source, f"{fld} {value!r} not recognised; expected one of +X, -X, +Y, -Y, +Z, -Z "
                                 "(+RX..-RZ for rotations, 'scalar') or a 3-vector")
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.linalg.norm(v) > 0:
        raise InputError(source, f"{fld} {value!r} not recognised; expected an axis string or a non-zero 3-vector")
    if abs(np.linalg.norm(v) - 1.0) > 1e-12:  # leave unit vectors be, so that a record re-checks to itself
        v = v / np.linalg.norm(v)
    return (float(v[0]), float(v[1]), float(v[2]))


def _code(direction: Direction) -> int:
    if isinstance(direction, str):
        return _DIR_CODE[direction]
    i = int(np.argmax(np.abs(direction)))  # the nearest axis; the vector itself goes to ID line 5
    return (i + 1) * (1 if direction[i] > 0 else -1)


def _array(value: Any, source: str, fld: str, dtype: Any, shape: tuple[int | None, ...]) -> np.ndarray:
    a = np.asarray(value)
    if a.ndim != len(shape) or any(n is not None and n != m for n, m in zip(shape, a.shape)):
        raise InputError(source, f"{fld} must have shape {shape} (None: any); got {a.shape}")
    if np.dtype(dtype).kind in "iu":
        if a.size and not np.all(np.asarray(a, float) == np.round(np.asarray(a, float))):
            raise InputError(source, f"{fld} must hold integers")
        return a.astype(np.int64)
    if np.dtype(dtype).kind == "f" and np.iscomplexobj(a):
        raise InputError(source, f"{fld} must be real")
    a = a.astype(dtype)
    if not np.all(np.isfinite(a)):
        raise InputError(source, f"{fld} holds {int(np.sum(~np.isfinite(a)))} NaN or infinite values")
    return a


def _name(name: Any, source: str) -> str:
    if not isinstance(name, str) or not name.strip(" .") or "/" in name or len(name) > 80:
        raise InputError(source, "name must be a non-empty string of at most 80 characters without '/'")
    return name


def _finite(value: Any, source: str, fld: str, low: float = -np.inf, high: float = np.inf) -> float:
    v = float(value)
    if not (np.isfinite(v) and low <= v <= high):
        raise InputError(source, f"{fld} = {value!r}; expected a finite number in [{low}, {high}]")
    return v


def _whole(value: Any, source: str, fld: str) -> int:
    v = _finite(value, source, fld, 0)
    if v != int(v):
        raise InputError(source, f"{fld} = {value!r}; expected a whole number")
    return int(v)


def _unit(unit: str, default: str, source: str) -> str:
    unit = unit or default
    if not isinstance(unit, str) or len(unit) > 20 or " " in unit:
        raise InputError(source, f"unit {unit!r} must be a string of at most 20 characters without spaces")
    return unit


def _even_axis(value: Any, source: str) -> np.ndarray:
    f = _array(value, source, "freq_hz", float, (None,))
    if len(f) < 2:
        raise InputError(source, "freq_hz needs at least 2 lines")
    step, df = np.diff(f), (f[-1] - f[0]) / (len(f) - 1)
    if not df > 0 or np.max(np.abs(step - df)) > 1e-6 * df:
        raise InputError(source, f"freq_hz is not uniformly spaced (steps {step.min():.6g} to {step.max():.6g} Hz);"
                                 " UFF 58 and odsplat FRFs need an even frequency axis")
    return f


def _tag(text: str, source: str, fld: str) -> str:
    """A short word for an ID-line tag: at most 20 characters, no spaces ("" allowed)."""
    if not isinstance(text, str) or len(text) > 20 or any(c.isspace() for c in text):
        raise InputError(source, f"{fld} {text!r} must be a string of at most 20 characters without spaces")
    return text


# ------------------------------------------------------------------------------------------------------ records

@dataclass(eq=False)
class Geometry:
    """Measurement nodes (labels > 0), their coordinates in metres, and optional trace lines between them."""

    node_ids: np.ndarray                          # (P,) int
    coords_m: np.ndarray                          # (P, 3)
    lines: list[tuple[int, int]] | None = None
    names: list[str] | None = None

    def __post_init__(self) -> None:
        self.node_ids = _array(self.node_ids, "geometry", "node_ids", np.int64, (None,))
        p = len(self.node_ids)
        self.coords_m = _array(self.coords_m, "geometry", "coords_m", float, (p, 3))
        if len(set(self.node_ids.tolist())) != p or (p and self.node_ids.min() < 1):
            raise InputError("geometry", "node_ids must be unique and positive (UFF labels)")
        if self.lines is not None:
            self.lines = [(int(a), int(b)) for a, b in self.lines]
            known = set(self.node_ids.tolist())
            bad = [ln for ln in self.lines if ln[0] == ln[1] or not set(ln) <= known]
            if bad:
                raise InputError("geometry", f"lines {bad[:3]} join a node to itself or to a node not in node_ids")
        if self.names is not None and len(self.names) != p:
            raise InputError("geometry", f"names has {len(self.names)} entries for {p} nodes")


@dataclass(eq=False)
class TimeSeries:
    """One evenly sampled channel at a node, in SI units (quantity: force, acceleration, velocity, displacement;
    files written by others may also give pressure or unknown)."""

    name: str
    node_id: int
    direction: Direction
    quantity: str
    unit: str
    t0_s: float
    dt_s: float
    values: np.ndarray                            # (N,)

    def __post_init__(self) -> None:
        src = f"time series {self.name!r}"
        self.name = _name(self.name, src)
        self.node_id = _whole(self.node_id, src, "node_id")
        self.direction = _direction(self.direction, src, "direction")
        if self.quantity not in _QUANTITY:
            raise InputError(src, f"quantity {self.quantity!r}; expected one of {sorted(_QUANTITY)}")
        self.unit = _unit(self.unit, _QUANTITY[self.quantity][2], src)
        self.t0_s = _finite(self.t0_s, src, "t0_s")
        self.dt_s = _finite(self.dt_s, src, "dt_s", 1e-300)
        self.values = _array(self.values, src, "values", float, (None,))
        if len(self.values) < 2:
            raise InputError(src, "values needs at least 2 samples")

    @property
    def time_s(self) -> np.ndarray:
        return self.t0_s + self.dt_s * np.arange(len(self.values))


@dataclass(eq=False)
class FRFRecord:
    """A frequency response function, response over reference, on an evenly spaced frequency axis. The unit
    defaults to the SI unit of the quantity (accelerance m/s^2/N, mobility m/s/N, receptance m/N)."""

    name: str
    response_node: int
    response_direction: Direction
    reference_node: int
    reference_direction: Direction
    quantity: str
    freq_hz: np.ndarray                           # (F,)
    values: np.ndarray                            # (F,) complex
    unit: str = ""

    def __post_init__(self) -> None:
        src = f"FRF {self.name!r}"
        self.name = _name(self.name, src)
        self.response_node = _whole(self.response_node, src, "response_node")
        self.reference_node = _whole(self.reference_node, src, "reference_node")
        self.response_direction = _direction(self.response_direction, src, "response_direction")
        self.reference_direction = _direction(self.reference_direction, src, "reference_direction")
        if self.quantity not in _FRF_NUMERATOR:
            raise InputError(src, f"quantity {self.quantity!r}; expected one of {sorted(_FRF_NUMERATOR)}")
        num = _QUANTITY[_FRF_NUMERATOR[self.quantity]][2]
        self.unit = _unit(self.unit, num + "/N" if num else "", src)
        self.freq_hz = _even_axis(self.freq_hz, src)
        self.values = _array(self.values, src, "values", complex, (len(self.freq_hz),))


@dataclass(eq=False)
class ShapeRecord:
    """A mode shape or an operational deflection shape: complex X, Y, Z amplitudes at nodes, at a frequency
    (natural frequency wn/2pi of a mode; the frequency line of an ODS), with a viscous damping ratio."""

    name: str
    freq_hz: float
    damping: float
    node_ids: np.ndarray                          # (P,) int
    values: np.ndarray                            # (P, 3) complex
    kind: str = "mode"
    unit: str = "m"
    number: int = 0              # mode number (modes) or frequency step number (ODS); 0: by order in its set
    shape_set: str = ""          # which instrument or analysis the shape is from ("accelerometers", "video")

    def __post_init__(self) -> None:
        src = f"shape {self.name!r}"
        self.name = _name(self.name, src)
        if self.kind not in ("mode", "ods"):
            raise InputError(src, f"kind {self.kind!r}; expected 'mode' or 'ods'")
        self.freq_hz = _finite(self.freq_hz, src, "freq_hz", 1e-300 if self.kind == "mode" else 0.0)
        self.damping = _finite(self.damping, src, "damping", 0.0, 0.999999)
        self.node_ids = _array(self.node_ids, src, "node_ids", np.int64, (None,))
        self.values = _array(self.values, src, "values", complex, (len(self.node_ids), 3))
        if len(set(self.node_ids.tolist())) != len(self.node_ids):
            raise InputError(src, "node_ids must be unique")
        self.unit = _unit(self.unit, "", src)
        self.number = _whole(self.number, src, "number")
        self.shape_set = _tag(self.shape_set, src, "shape_set")


@dataclass(eq=False)
class CoherenceRecord:
    """The ordinary coherence of one response with the reference, on an even frequency axis (dimensionless,
    0..1), as estimated beside the FRF of the same pair of nodes."""

    name: str
    response_node: int
    response_direction: Direction
    reference_node: int
    reference_direction: Direction
    freq_hz: np.ndarray                           # (F,)
    values: np.ndarray                            # (F,) real

    def __post_init__(self) -> None:
        src = f"coherence {self.name!r}"
        self.name = _name(self.name, src)
        self.response_node = _whole(self.response_node, src, "response_node")
        self.reference_node = _whole(self.reference_node, src, "reference_node")
        self.response_direction = _direction(self.response_direction, src, "response_direction")
        self.reference_direction = _direction(self.reference_direction, src, "reference_direction")
        self.freq_hz = _even_axis(self.freq_hz, src)
        self.values = _array(self.values, src, "values", float, (len(self.freq_hz),))
        if self.values.size and not (self.values.min() >= -1e-9 and self.values.max() <= 1 + 1e-9):
            raise InputError(src, f"values from {self.values.min():.6g} to {self.values.max():.6g}; a coherence "
                                  "lies in [0, 1]")


@dataclass(eq=False)
class MACRecord:
    """Two sets of shapes compared at the same degrees of freedom: the MAC matrix (rows: set a, columns: set b,
    each labelled by its mode number), the pairs taken from it with their MAC, modal scale factor (a ~ s b) and
    frequencies (NaN where a set has none), and the CoMAC per coordinate (node) over the pairs."""

    name: str
    mac: np.ndarray                               # (A, B)
    modes_a: np.ndarray                           # (A,) int
    modes_b: np.ndarray                           # (B,) int
    pairs: np.ndarray                             # (K, 2) int: (row, column) indices into mac
    pair_mac: np.ndarray                          # (K,)
    scale_factor: np.ndarray                      # (K,) complex
    pair_freq_a_hz: np.ndarray                    # (K,), NaN: unknown
    pair_freq_b_hz: np.ndarray                    # (K,)
    comac: np.ndarray                             # (D,)
    comac_nodes: np.ndarray                       # (D,) int: the node of each coordinate
    label_a: str = ""
    label_b: str = ""

    def __post_init__(self) -> None:
        src = f"MAC {self.name!r}"
        self.name = _name(self.name, src)
        self.mac = _array(self.mac, src, "mac", float, (None, None))
        a, b = self.mac.shape
        self.modes_a = _array(self.modes_a, src, "modes_a", np.int64, (a,))
        self.modes_b = _array(self.modes_b, src, "modes_b", np.int64, (b,))
        self.pairs = _array(np.reshape(self.pairs, (-1, 2)), src, "pairs", np.int64, (None, 2))
        k = len(self.pairs)
        if k and not (np.all(self.pairs >= 0) and np.all(self.pairs[:, 0] < a) and np.all(self.pairs[:, 1] < b)):
            raise InputError(src, f"pairs must index the ({a}, {b}) MAC matrix")
        self.pair_mac = _array(self.pair_mac, src, "pair_mac", float, (k,))
        self.scale_factor = _array(self.scale_factor, src, "scale_factor", complex, (k,))
        for fld in ("pair_freq_a_hz", "pair_freq_b_hz"):       # NaN is allowed: a frequency not found
            v = np.asarray(getattr(self, fld), float)
            if v.shape != (k,) or np.any(np.isinf(v)):
                raise InputError(src, f"{fld} must be ({k},) finite or NaN; got shape {v.shape}")
            setattr(self, fld, v)
        self.comac = _array(self.comac, src, "comac", float, (None,))
        self.comac_nodes = _array(self.comac_nodes, src, "comac_nodes", np.int64, (len(self.comac),))
        self.label_a, self.label_b = str(self.label_a), str(self.label_b)


@dataclass(eq=False)
class StabilisationRecord:
    """A stabilisation chart: every pole of every model order with its status against the previous order
    ("stable", "damping", "freq", "new"), and the poles selected from it. Poles in rad/s, as fitted."""

    name: str
    order: np.ndarray                             # (P,) int
    poles_rad_s: np.ndarray                       # (P,) complex
    status: np.ndarray                            # (P,) str
    selected_rad_s: np.ndarray                    # (M,) complex
    freq_tol: float = 0.01
    damping_tol: float = 0.05
    window_tau_s: float = 0.0    # the exponential window's time constant (0: none): the chart's poles carry its
    #                              1/tau of added decay rate; modes corrected for it differ by that much

    def __post_init__(self) -> None:
        src = f"stabilisation {self.name!r}"
        self.name = _name(self.name, src)
        self.order = _array(self.order, src, "order", np.int64, (None,))
        self.poles_rad_s = _array(self.poles_rad_s, src, "poles_rad_s", complex, (len(self.order),))
        status = np.asarray([s.decode() if isinstance(s, bytes) else str(s) for s in np.ravel(self.status)])
        if status.shape != self.order.shape or not set(status.tolist()) <= set(_STATUSES):
            raise InputError(src, f"status must hold one of {_STATUSES} per pole")
        self.status = status.astype(str)
        self.selected_rad_s = _array(self.selected_rad_s, src, "selected_rad_s", complex, (None,))
        self.freq_tol = _finite(self.freq_tol, src, "freq_tol", 0.0)
        self.damping_tol = _finite(self.damping_tol, src, "damping_tol", 0.0)
        self.window_tau_s = _finite(self.window_tau_s, src, "window_tau_s", 0.0)

    @property
    def freq_hz(self) -> np.ndarray:
        """Undamped natural frequency |lambda| / 2 pi of each pole."""
        return np.abs(self.poles_rad_s) / (2 * np.pi)

    @property
    def damping(self) -> np.ndarray:
        """Viscous damping ratio -Re(lambda) / |lambda| of each pole."""
        mag = np.abs(self.poles_rad_s)
        return -self.poles_rad_s.real / np.where(mag > 0, mag, 1.0)


@dataclass(eq=False)
class ResultSet:
    """What a results file holds; `skipped` lists the datasets of a foreign UFF that were not read, and why."""

    geometry: Geometry | None = None
    time_series: list[TimeSeries] = field(default_factory=list)
    frfs: list[FRFRecord] = field(default_factory=list)
    shapes: list[ShapeRecord] = field(default_factory=list)
    coherence: list[CoherenceRecord] = field(default_factory=list)
    mac: list[MACRecord] = field(default_factory=list)                  # results.h5 only
    stabilisation: list[StabilisationRecord] = field(default_factory=list)  # results.h5 only
    description: str = ""
    attrs: dict[str, Any] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)


_KINDS = {"time_series": ("time series", TimeSeries), "frfs": ("FRF", FRFRecord), "shapes": ("shape", ShapeRecord),
          "coherence": ("coherence", CoherenceRecord), "mac": ("MAC", MACRecord),
          "stabilisation": ("stabilisation", StabilisationRecord)}


def _shape_numbers(shapes: Sequence[ShapeRecord]) -> list[tuple[int, int]]:
    """(load case, number) of each shape: its set's place among the sets (1, 2, ...), and its given number or its
    place among its set's shapes of its kind. Two shapes of one set and kind may not share a number."""
    cases: dict[str, int] = {}
    count: dict[tuple[str, str], int] = {}
    seen: dict[tuple[str, str, int], str] = {}
    out = []
    for r in shapes:
        case = cases.setdefault(r.shape_set, len(cases) + 1)
        key = (r.shape_set, r.kind)
        count[key] = count.get(key, 0) + 1
        n = r.number or count[key]
        if (*key, n) in seen:
            raise InputError(f"shape {r.name!r}", f"{r.kind} number {n} of set {r.shape_set!r} is also "
                                                  f"{seen[(*key, n)]!r}'s; numbers are unique within a set")
        seen[(*key, n)] = r.name
        out.append((case, n))
    return out


def _check_records(geometry: Geometry | None, records: dict[str, list]) -> None:
    for group, recs in records.items():
        kind, cls = _KINDS[group]
        names = []
        for r in recs:
            if not isinstance(r, cls):
                raise InputError(kind, f"expected {cls.__name__} records; got {type(r).__name__}")
            r.__post_init__()  # records are mutable: check them again as they are now
            if r.name in names:
                raise InputError(f"{kind} {r.name!r}", "name used by more than one record; names must be unique")
            names.append(r.name)
    _shape_numbers(records.get("shapes", ()))
    if geometry is not None:
        geometry.__post_init__()
        known = set(geometry.node_ids.tolist())
        for s in records.get("shapes", ()):
            missing = sorted(set(s.node_ids.tolist()) - known)
            if missing:
                raise InputError(f"shape {s.name!r}", f"node_ids {missing[:5]} are not in the geometry")


# ------------------------------------------------------------------------------------------------------- UFF out

def _uff_date() -> str:
    t = time.localtime()  # not strftime: %b follows the locale, UFF wants English months
    return f"{t.tm_mday:02d}-{_MONTHS[t.tm_mon - 1]}-{t.tm_year % 100:02d} " + time.strftime("%H:%M:%S", t)


def _vector_tags(**dirs: Direction) -> str:
    tags = [f"{k}=({v[0]:.6f},{v[1]:.6f},{v[2]:.6f})" for k, v in dirs.items() if not isinstance(v, str)]
    return " ".join(tags) or "NONE"


def _dset58(*, func_type: int, name: str, id2: str, id3: str, id5: str, rsp: tuple[int, int], ref: tuple[int, int],
            x: np.ndarray, data: np.ndarray, abscissa: tuple[int, str, str], ordinate: tuple[int, str, str],
            denominator: tuple[int, str, str]) -> dict:
    d = pyuff.prepare_58(
        binary=0, id1=name, id2=id2, id3=id3, id4="NONE", id5=id5, func_type=func_type, load_case_id=0,
        rsp_ent_name="NONE", rsp_node=rsp[0], rsp_dir=rsp[1], ref_ent_name="NONE", ref_node=ref[0], ref_dir=ref[1],
        abscissa_spacing=1, abscissa_spec_data_type=abscissa[0], abscissa_axis_units_lab=abscissa[2],
        ordinate_spec_data_type=ordinate[0], ordinate_axis_units_lab=ordinate[2] or "NONE",
        orddenom_spec_data_type=denominator[0], orddenom_axis_units_lab=denominator[2],
        z_axis_spec_data_type=0, x=x, data=data)
    d.update(abscissa_axis_lab=abscissa[1], ordinate_axis_lab=ordinate[1], orddenom_axis_lab=denominator[1])
    return d


def _ts_dset(ts: TimeSeries, id2: str, id3: str) -> dict:
    spec, label, _ = _QUANTITY[ts.quantity]
    return _dset58(func_type=1, name=ts.name, id2=id2, id3=id3, id5=_vector_tags(rsp=ts.direction),
                   rsp=(ts.node_id, _code(ts.direction)), ref=(0, 0), x=ts.time_s, data=ts.values,
                   abscissa=(17, "Time", "s"), ordinate=(spec, label, ts.unit), denominator=(0, "NONE", "NONE"))


def _frf_dset(frf: FRFRecord, id2: str, id3: str) -> dict:
    spec, label, _ = _QUANTITY[_FRF_NUMERATOR[frf.quantity]]
    num, den = (frf.unit[:-2], (13, "Force", "N")) if frf.unit.endswith("/N") else (frf.unit, (0, "NONE", "NONE"))
    return _dset58(func_type=4, name=frf.name, id2=id2, id3=id3,
                   id5=_vector_tags(rsp=frf.response_direction, ref=frf.reference_direction),
                   rsp=(frf.response_node, _code(frf.response_direction)),
                   ref=(frf.reference_node, _code(frf.reference_direction)), x=frf.freq_hz, data=frf.values,
                   abscissa=(18, "Frequency", "Hz"), ordinate=(spec, label, num),
                   denominator=den if spec else (0, "NONE", den[2]))


def _coherence_dset(c: CoherenceRecord, id2: str, id3: str) -> dict:
    return _dset58(func_type=6, name=c.name, id2=id2, id3=id3,
                   id5=_vector_tags(rsp=c.response_direction, ref=c.reference_direction),
                   rsp=(c.response_node, _code(c.response_direction)),
                   ref=(c.reference_node, _code(c.reference_direction)), x=c.freq_hz, data=c.values,
                   abscissa=(18, "Frequency", "Hz"), ordinate=(0, "Coherence", "NONE"),
                   denominator=(0, "NONE", "NONE"))


def _shape_dset(s: ShapeRecord, case: int, n: int, id2: str, id3: str) -> dict:
    base = s.unit[:-2] if s.unit.endswith("/N") else s.unit
    spec = {"m": 8, "m/s": 11, "m/s^2": 12}.get(base, 0)
    real = not np.any(s.values.imag)
    v = s.values.real if real else s.values
    id4 = f"odsplat {s.kind} unit={s.unit or 'NONE'}" + (f" set={s.shape_set}" if s.shape_set else "")
    common = dict(id1=s.name, id2=id2, id3=id3, id4=id4, model_type=1, data_ch=2, spec_data_type=spec,
                  node_nums=s.node_ids, load_case=case, r1=v[:, 0], r2=v[:, 1], r3=v[:, 2])
    if s.kind == "ods":
        if s.damping:
            log.warning("shape %r: an ODS record (UFF 55 analysis type 5) carries no damping; %g dropped",
                        s.name, s.damping)
        return pyuff.prepare_55(analysis_type=5, freq_step_n=n, freq=s.freq_hz,
                                id5=f"ODS {n:10d} Frequency {s.freq_hz:13.5e}", **common)
    id5 = f"Mode {n:10d} Frequency {s.freq_hz:13.5e} Damping {s.damping:13.5e}"
    if real:
        return pyuff.prepare_55(analysis_type=2, mode_n=n, freq=s.freq_hz, modal_m=0.0, modal_damp_vis=s.damping,
                                modal_damp_his=0.0, id5=id5, **common)
    wn = 2 * np.pi * s.freq_hz
    eig = complex(-s.damping * wn, wn * np.sqrt(1 - s.damping ** 2))
    return pyuff.prepare_55(analysis_type=3, mode_n=n, eig=eig, modal_a=0j, modal_b=0j, id5=id5, **common)


def write_uff(path: str | Path, *, geometry: Geometry | None = None, time_series: Sequence[TimeSeries] = (),
              frfs: Sequence[FRFRecord] = (), shapes: Sequence[ShapeRecord] = (),
              coherence: Sequence[CoherenceRecord] = (), description: str = "") -> Path:
    """Write the records to one ASCII universal file (atomically: a failure leaves no partial file). Each
    coherence follows the FRFs; MAC and stabilisation records have no UFF dataset (results.h5 holds them)."""
    path = Path(path)
    time_series, frfs, shapes, coherence = list(time_series), list(frfs), list(shapes), list(coherence)
    _check_records(geometry, {"time_series": time_series, "frfs": frfs, "shapes": shapes, "coherence": coherence})
    if geometry is None and not (time_series or frfs or shapes or coherence):
        raise InputError(path, "nothing to write: no geometry, time series, FRFs, coherence or shapes")
    id2, id3 = (description.strip()[:80] or "NONE"), _uff_date()
    sets: list[tuple[str, dict]] = [
        ("header", pyuff.prepare_151(model_name=description.strip()[:80] or "NONE",
                                     description="Units: SI (m, N, s, Hz, m/s^2, Pa); written by odsplat",
                                     db_app="odsplat", program="odsplat")),
        ("units", pyuff.prepare_164(units_code=1, units_description="SI: Meter (newton)", temp_mode=2,
                                    length=1.0, force=1.0, temp=1.0, temp_offset=273.15))]
    if geometry is not None:
        g, zeros = geometry, np.zeros(len(geometry.node_ids), dtype=int)
        sets.append(("geometry nodes", pyuff.prepare_2411(node_nums=g.node_ids, def_cs=zeros, disp_cs=zeros,
                                                          color=zeros + 8, x=g.coords_m[:, 0], y=g.coords_m[:, 1],
                                                          z=g.coords_m[:, 2])))
        for k in range(0, len(g.lines or ()), 83):  # Artemis' form, "0 a b" per line: at most 249 entries a set
            nodes = np.array([[0, a, b] for a, b in g.lines[k:k + 83]]).reshape(-1)
            sets.append((f"trace lines {k // 83 + 1}", pyuff.prepare_82(trace_num=k // 83 + 1, n_nodes=len(nodes),
                                                                        color=8, id="odsplat geometry", nodes=nodes)))
    sets += [(f"time series {r.name!r}", _ts_dset(r, id2, id3)) for r in time_series]
    sets += [(f"FRF {r.name!r}", _frf_dset(r, id2, id3)) for r in frfs]
    sets += [(f"coherence {r.name!r}", _coherence_dset(r, id2, id3)) for r in coherence]
    sets += [(f"shape {s.name!r}", _shape_dset(s, case, n, id2, id3))
             for s, (case, n) in zip(shapes, _shape_numbers(shapes))]
    with atomic_path(path) as tmp:
        uff = pyuff.UFF(str(tmp))
        for i, (label, dset) in enumerate(sets):
            try:
                uff.write_sets([dset], mode="overwrite" if i == 0 else "add")
            except Exception as exc:  # pyuff raises bare Exceptions
                raise OdsplatError(f"{path}: pyuff could not write the {label} dataset {dset['type']}: {exc}") from exc
    log.info("%s: wrote %d UFF datasets", path, len(sets))
    return path


# -------------------------------------------------------------------------------------------------------- UFF in

def _label(text: Any) -> str:
    text = str(text or "").strip()
    return "" if text.upper() == "NONE" else text


def _unique(name: str, fallback: str, taken: set[str]) -> str:
    name = (_label(name).replace("/", "_")[:80].strip() or fallback)
    out, k = name, 2
    while out in taken:
        out, k = f"{name[:74]} ({k})", k + 1
    taken.add(out)
    return out


def _directions(d: dict, id5: str) -> dict[str, Direction]:
    vectors = {m.group(1): tuple(float(c) for c in m.group(2).split(",")) for m in _VECTOR_TAG.finditer(id5)}
    return {k: vectors.get(k, _CODE_DIR.get(int(d[f"{k}_dir"]), "scalar")) for k in ("rsp", "ref")}


def _from_58(d: dict, i: int, taken: set[str]) -> TimeSeries | FRFRecord | CoherenceRecord:
    ft, src = int(d["func_type"]), f"dataset #{i} (58, {_label(d.get('id1')) or 'unnamed'})"
    if ft not in (1, 4, 6):
        raise InputError(src, f"function type {ft} is not a time response (1), an FRF (4) or a coherence (6)")
    n = len(d["data"])
    if int(d["abscissa_spacing"]) == 1:
        x0, dx = float(d["abscissa_min"]), float(d["abscissa_inc"])
    else:
        x = np.asarray(d["x"], float)
        x0, dx = float(x[0]), float((x[-1] - x[0]) / max(n - 1, 1))
        if n < 2 or np.max(np.abs(np.diff(x) - dx)) > 1e-4 * abs(dx):
            raise InputError(src, "uneven abscissa; odsplat records need even spacing")
    dirs = _directions(d, _label(d.get("id5")))
    num, den = _label(d.get("ordinate_axis_units_lab")), _label(d.get("orddenom_axis_units_lab"))
    quantity = _SPEC_QUANTITY.get(int(d["ordinate_spec_data_type"]), "unknown")
    data = np.asarray(d["data"])
    fallback = {1: "time", 4: "frf", 6: "coherence"}[ft]
    name = _unique(_label(d.get("id1")) or _label(d.get("rsp_ent_name")), f"{fallback} {i}", taken)
    if ft == 6:
        if np.iscomplexobj(data) and np.any(data.imag):
            raise InputError(src, "a coherence with complex values")
        return CoherenceRecord(name, int(d["rsp_node"]), dirs["rsp"], int(d["ref_node"]), dirs["ref"],
                               x0 + dx * np.arange(n), data.real.astype(float))
    if ft == 1:
        if np.iscomplexobj(data) and np.any(data.imag):
            raise InputError(src, "a time response with complex values")
        return TimeSeries(name, int(d["rsp_node"]), dirs["rsp"], quantity, num.replace(" ", ""), x0, dx,
                          data.real.astype(float))
    frf_q = {v: k for k, v in _FRF_NUMERATOR.items()}.get(quantity, "unknown")
    if int(d["orddenom_spec_data_type"]) not in (9, 13):
        frf_q = "unknown"
    unit = (f"{num}/{den}" if num and den else num or den).replace(" ", "")[:20]
    return FRFRecord(name, int(d["rsp_node"]), dirs["rsp"], int(d["ref_node"]), dirs["ref"], frf_q,
                     x0 + dx * np.arange(n), data.astype(complex), unit=unit)


def _from_55(d: dict, i: int, taken: set[str]) -> ShapeRecord:
    at, src = int(d["analysis_type"]), f"dataset #{i} (55, {_label(d.get('id1')) or 'unnamed'})"
    if int(d.get("data_ch", 2)) not in (2, 3) or "r3" not in d:
        raise InputError(src, f"data characteristic {d.get('data_ch')} is not a 3- or 6-DOF vector")
    values = np.stack([np.asarray(d[k], complex) for k in ("r1", "r2", "r3")], axis=1)
    id4 = _label(d.get("id4"))
    tag, set_tag = _UNIT_TAG.search(id4), _SET_TAG.search(id4)
    unit = _label(tag.group(1)) if tag else {8: "m", 11: "m/s", 12: "m/s^2"}.get(int(d["spec_data_type"]), "")
    shape_set = set_tag.group(1)[:20] if set_tag else ""
    if at == 2:
        kind, n, freq, damping = "mode", d["mode_n"], d["freq"], d.get("modal_damp_vis", 0.0)
    elif at in (3, 7):
        eig = complex(d["eig"])
        kind, n, freq, damping = "mode", d["mode_n"], abs(eig) / (2 * np.pi), -eig.real / abs(eig) if eig else 0.0
    elif at == 5:
        kind, n, freq, damping = "ods", d["freq_step_n"], d["freq"], 0.0
    else:
        raise InputError(src, f"analysis type {at} is not a mode (2, 3, 7) or a frequency response (5)")
    name = _unique(d.get("id1"), f"{kind} {n}", taken)
    return ShapeRecord(name, freq, damping, np.asarray(d["node_nums"]).astype(np.int64), values, kind, unit,
                       number=max(int(n), 0), shape_set=shape_set)


def read_uff(path: str | Path) -> ResultSet:
    """Read nodes (2411 or 15), trace lines (82), time responses, FRFs and coherence (58, 58b) and shapes (55)
    from a universal file. Datasets of other kinds, or that do not fit the records, are listed in `skipped`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        uff = pyuff.UFF(str(path))
        types = [int(t) for t in uff.get_set_types()]
    except Exception as exc:
        raise InputError(path, f"not a readable universal file ({exc})") from exc
    if not types:
        raise InputError(path, "not a universal file (UFF): no datasets delimited by '    -1' lines")
    out, taken = ResultSet(), {"58": set(), "55": set()}
    nodes: list[tuple[np.ndarray, np.ndarray]] = []
    lines: list[tuple[int, int]] = []
    length_factor = 1.0
    for i, t in enumerate(types):
        if t not in (15, 55, 58, 82, 151, 164, 2411):
            out.skipped.append(f"dataset #{i}: type {t} is not read")
            continue
        try:
            d = uff.read_sets(i)
        except Exception as exc:
            raise InputError(path, f"dataset #{i} (type {t}) is unreadable: {exc}") from exc
        if t == 151:
            out.description = _label(d.get("model_name"))
        elif t == 164:
            length_factor = float(d["length"]) or 1.0  # file units per metre
        elif t in (15, 2411):
            nodes.append((np.asarray(d["node_nums"], float).astype(np.int64),
                          np.stack([d["x"], d["y"], d["z"]], axis=1).astype(float)))
        elif t == 82:
            seq = np.asarray(d["nodes"], float).astype(np.int64).tolist()
            lines += [(a, b) for a, b in zip(seq[:-1], seq[1:]) if a and b]
        else:
            try:
                rec = _from_58(d, i, taken["58"]) if t == 58 else _from_55(d, i, taken["55"])
            except InputError as exc:
                out.skipped.append(str(exc))
                log.warning("%s: skipped %s", path, exc)
                continue
            {TimeSeries: out.time_series, FRFRecord: out.frfs, ShapeRecord: out.shapes,
             CoherenceRecord: out.coherence}[type(rec)].append(rec)
    if nodes:
        ids, coords = np.concatenate([n[0] for n in nodes]), np.concatenate([n[1] for n in nodes]) / length_factor
        known = set(ids.tolist())
        try:
            out.geometry = Geometry(ids, coords, [ln for ln in lines if set(ln) <= known] if lines else None)
        except InputError as exc:
            raise InputError(path, f"nodes (2411/15): {exc.problem}") from exc
    if out.geometry is None and not (out.time_series or out.frfs or out.shapes or out.coherence):
        raise InputError(path, f"holds no nodes, functions (58) or shapes (55) odsplat can read; dataset types "
                               f"{sorted(set(types))}" + (f"; skipped: {out.skipped[:3]}" if out.skipped else ""))
    return out


# ------------------------------------------------------------------------------------------------------- HDF5

_RESERVED = ("kind", "schema_version", "created_utc", "json_attrs", CAPTURE_KEY)
# What h5py raises reading a file that is cut short or damaged: OSError (a chunk, a heap), KeyError (an object
# header), RuntimeError, ValueError and TypeError (a garbled attribute, type or shape).
_H5_ERRORS = (OSError, KeyError, RuntimeError, ValueError, TypeError, IndexError, AttributeError)


def _plain(value: Any) -> Any:
    """An HDF5 attribute as Python: str, int, float, or a direction vector as a tuple."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return tuple(float(c) for c in value)
    return value.item() if isinstance(value, np.generic) else value


def write_results_h5(path: str | Path, *, geometry: Geometry | None = None, time_series: Sequence[TimeSeries] = (),
                     frfs: Sequence[FRFRecord] = (), shapes: Sequence[ShapeRecord] = (),
                     coherence: Sequence[CoherenceRecord] = (), mac: Sequence[MACRecord] = (),
                     stabilisation: Sequence[StabilisationRecord] = (), attrs: dict[str, Any] | None = None,
                     capture_id: str | None = None) -> Path:
    """Write the records to an HDF5 file in the layout of the module docstring (atomically); `capture_id`: the
    capture the results are of, recorded for `read_results_h5` to check."""
    path = Path(path)
    records = {"time_series": list(time_series), "frfs": list(frfs), "shapes": list(shapes),
               "coherence": list(coherence), "mac": list(mac), "stabilisation": list(stabilisation)}
    attrs = dict(attrs or {})
    _check_records(geometry, records)
    if set(_RESERVED) & set(attrs):
        raise InputError("attrs", f"{sorted(set(_RESERVED) & set(attrs))} are reserved by the results layout")
    json_keys = [k for k, v in attrs.items() if v is None or isinstance(v, (dict, list, tuple))]
    with atomic_path(path) as tmp, writing_h5(tmp, "w", track_order=True) as f:
        f.attrs.update({"kind": RESULTS_KIND, "schema_version": RESULTS_SCHEMA, "json_attrs": json.dumps(json_keys),
                        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")})
        if capture_id is not None:
            f.attrs[CAPTURE_KEY] = capture_id
        f.attrs.update({k: json.dumps(v) if k in json_keys else v for k, v in attrs.items()})
        if geometry is not None:
            g = f.create_group("geometry", track_order=True)
            _checksummed(g, "node_ids", geometry.node_ids)
            _checksummed(g, "coords_m", geometry.coords_m).attrs["unit"] = "m"
            if geometry.lines is not None:
                _checksummed(g, "lines", np.asarray(geometry.lines, np.int64).reshape(-1, 2))
            if geometry.names is not None:
                g.create_dataset("names", data=list(geometry.names), dtype=h5py.string_dtype())
        for group, recs in records.items():
            parent = f.create_group(group, track_order=True) if recs else None
            for r in recs:
                g = parent.create_group(r.name, track_order=True)
                for fld in fields(r):
                    value = getattr(r, fld.name)
                    if isinstance(value, np.ndarray) and value.dtype.kind == "U":
                        g.create_dataset(fld.name, data=value.tolist(), dtype=h5py.string_dtype())
                    elif isinstance(value, np.ndarray):
                        _checksummed(g, fld.name, value)
                    elif fld.name != "name":
                        g.attrs[fld.name] = np.asarray(value, float) if isinstance(value, tuple) else value
    return path


def _checksummed(g: h5py.Group, name: str, value: np.ndarray) -> h5py.Dataset:
    """A numeric array with a Fletcher-32 checksum per chunk (where it has elements), so that damage reads as an
    error, never as other numbers."""
    value = np.asarray(value)
    return g.create_dataset(name, data=value, fletcher32=value.ndim > 0 and value.size > 0)


def _h5_record(cls: type, name: str, g: h5py.Group) -> Any:
    """One record from its group; a field a schema-2 file lacks takes the record's default."""
    kw = {}
    for fld in fields(cls):
        if fld.name == "name":
            continue
        if fld.name in g:
            ds = g[fld.name]
            kw[fld.name] = ds.asstr()[()] if h5py.check_string_dtype(ds.dtype) else ds[()]
        elif fld.name in g.attrs:
            kw[fld.name] = _plain(g.attrs[fld.name])
        elif fld.default is MISSING:
            raise KeyError(f"{g.name}/{fld.name}")
    return cls(name=name, **kw)


def read_results_h5(path: str | Path, capture_id: str | None = None) -> ResultSet:
    """Read a file written by `write_results_h5`; given `capture_id`, a file that records another capture's is
    refused. Whatever is wrong with the file (empty, cut short, not HDF5, damaged, a record incomplete or of the
    wrong shape or type) is one line naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes), not a results file; run `odsplat analyze` again")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(path, f"not an HDF5 file, or cut short ({' '.join(str(exc).split())})") from None
    with f:
        try:
            return _read_results(f, path, capture_id)
        except OdsplatError as exc:
            if str(path) in str(exc):
                raise
            raise InputError(path, f"{exc}; run `odsplat analyze` again") from None
        except _H5_ERRORS as exc:
            raise InputError(path, f"not a readable results file, cut short or damaged ({type(exc).__name__}: "
                                   f"{' '.join(str(exc).split())[:200]}); run `odsplat analyze` again") from None


def _read_results(f: h5py.File, path: Path, capture_id: str | None) -> ResultSet:
    if _plain(f.attrs.get("kind")) != RESULTS_KIND:
        raise InputError(path, f"not an {RESULTS_KIND} file (kind={_plain(f.attrs.get('kind'))!r})")
    version = _plain(f.attrs.get("schema_version"))
    if version not in READABLE_SCHEMAS:
        raise SchemaError(path, f"results schema {version}; this odsplat reads "
                                f"{', '.join(str(v) for v in READABLE_SCHEMAS)}")
    check_capture(f.attrs.get(CAPTURE_KEY), path, capture_id)
    try:
        json_keys = json.loads(_plain(f.attrs.get("json_attrs", "[]")))
        out = ResultSet(attrs={k: json.loads(v) if k in json_keys else _plain(v) for k, v in f.attrs.items()
                               if k not in _RESERVED})
    except (json.JSONDecodeError, TypeError) as exc:
        raise InputError(path, f"attributes: not the JSON text the results layout stores ({exc})") from None
    try:
        if "geometry" in f:
            g = f["geometry"]
            lines = [(int(a), int(b)) for a, b in g["lines"][()]] if "lines" in g else None
            names = [_plain(s) for s in g["names"][()]] if "names" in g else None
            out.geometry = Geometry(g["node_ids"][()], g["coords_m"][()], lines, names)
        for group, (_, cls) in _KINDS.items():
            for name, g in f.get(group, {}).items():
                getattr(out, group).append(_h5_record(cls, name, g))
    except KeyError as exc:
        raise InputError(path, f"incomplete results file: {exc}") from None
    return out
