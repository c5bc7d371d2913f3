"""Export of test results (geometry, time series, FRFs, mode shapes and ODS) to universal files (UFF) and to a
documented HDF5 layout, and back, through plain records that do not depend on how the analysis made them.
The records here are the format-independent part: `Geometry`, `TimeSeries`, `FRFRecord`, `ShapeRecord`,
`CoherenceRecord`, `MACRecord`, `StabilisationRecord` and `ResultSet`, each checked as it is made. Their files:
`uff.py` (UFF, through pyuff) and `results_h5.py` (our HDF5 layout).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from odsplat.spine.errors import InputError

log = logging.getLogger(__name__)

# UFF direction codes (58 record 6): 1..3 translations, 4..6 rotations, 0 scalar.
_DIR_CODE = {"scalar": 0, **{f"{s}{a}": (1 if s == "+" else -1) * (i + 1) for s in "+-"
                             for i, a in enumerate(("X", "Y", "Z", "RX", "RY", "RZ"))}}
# quantity -> (UFF specific data type, axis label, SI unit)
_QUANTITY = {"displacement": (8, "Displacement", "m"), "velocity": (11, "Velocity", "m/s"),
             "acceleration": (12, "Acceleration", "m/s^2"), "force": (13, "Force", "N"),
             "pressure": (15, "Pressure", "Pa"), "unknown": (0, "NONE", "")}
_FRF_NUMERATOR = {"receptance": "displacement", "mobility": "velocity", "accelerance": "acceleration",
                  "unknown": "unknown"}
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
