"""Export of test results (geometry, time series, FRFs, mode shapes and ODS) to universal files (UFF) and to a
documented HDF5 layout, and back, through plain records that do not depend on how the analysis made them.

UFF (`write_uff` / `read_uff`, through pyuff): 151 header and 164 units (SI: metre, newton, second), 2411 nodes
(metres), 82 trace lines, 58 functions (function type 1 time response, 4 FRF; double precision, complex FRFs),
55 shapes (3-DOF translation vectors; real modes as analysis type 2 with frequency and viscous damping ratio,
complex modes as type 3 with the eigenvalue -zeta*wn + i*wn*sqrt(1-zeta^2) in rad/s, ODS as type 5 at a
frequency line). Headers hold 6 significant digits (E13.5): abscissa start and step, frequencies, dampings and
all of dataset 55; ordinates of 58 hold 12. ID line 1 is the record's name; an `odsplat unit=...` tag in ID
line 4 of a 55 keeps its unit, and a direction given as a vector is kept in ID line 5 (`rsp=(x,y,z)`).

HDF5 layout (`write_results_h5` / `read_results_h5`), groups kept in the order written::

    /                      attrs kind="odsplat.results", schema_version=2, created_utc, json_attrs (the
                           names of the user attrs stored as JSON text), then the user attrs
    /geometry              node_ids (P,) int64, coords_m (P,3) float64 [attr unit="m"],
                           lines (L,2) int64 (when given), names (P,) utf-8 (when given)
    /time_series/<name>    values (N,) float64; attrs node_id, direction, quantity, unit, t0_s, dt_s
    /frfs/<name>           freq_hz (F,) float64, values (F,) complex128; attrs response_node,
                           response_direction, reference_node, reference_direction, quantity, unit
    /shapes/<name>         node_ids (P,) int64, values (P,3) complex128 (X, Y, Z); attrs freq_hz, damping,
                           kind ("mode"|"ods"), unit

A direction attr is a string ("+X", "-Z", "scalar", ...) or a float64 unit vector (3,).
"""
from __future__ import annotations

import json
import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pyuff

from odsplat.errors import InputError, OdsplatError, SchemaError
from odsplat.store import atomic_path

log = logging.getLogger(__name__)

RESULTS_KIND = "odsplat.results"
RESULTS_SCHEMA = 2
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
        self.freq_hz = _array(self.freq_hz, src, "freq_hz", float, (None,))
        self.values = _array(self.values, src, "values", complex, (len(self.freq_hz),))
        f = self.freq_hz
        if len(f) < 2:
            raise InputError(src, "freq_hz needs at least 2 lines")
        step, df = np.diff(f), (f[-1] - f[0]) / (len(f) - 1)
        if not df > 0 or np.max(np.abs(step - df)) > 1e-6 * df:
            raise InputError(src, f"freq_hz is not uniformly spaced (steps {step.min():.6g} to {step.max():.6g} Hz);"
                                  " UFF 58 and odsplat FRFs need an even frequency axis")


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


@dataclass(eq=False)
class ResultSet:
    """What a results file holds; `skipped` lists the datasets of a foreign UFF that were not read, and why."""

    geometry: Geometry | None = None
    time_series: list[TimeSeries] = field(default_factory=list)
    frfs: list[FRFRecord] = field(default_factory=list)
    shapes: list[ShapeRecord] = field(default_factory=list)
    description: str = ""
    attrs: dict[str, Any] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)


def _check_records(geometry, time_series, frfs, shapes) -> None:
    for kind, cls, recs in (("time series", TimeSeries, time_series), ("FRF", FRFRecord, frfs),
                            ("shape", ShapeRecord, shapes)):
        names = []
        for r in recs:
            if not isinstance(r, cls):
                raise InputError(kind, f"expected {cls.__name__} records; got {type(r).__name__}")
            r.__post_init__()  # records are mutable: check them again as they are now
            if r.name in names:
                raise InputError(f"{kind} {r.name!r}", "name used by more than one record; names must be unique")
            names.append(r.name)
    if geometry is not None:
        geometry.__post_init__()
        known = set(geometry.node_ids.tolist())
        for s in shapes:
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


def _shape_dset(s: ShapeRecord, n: int, id2: str, id3: str) -> dict:
    base = s.unit[:-2] if s.unit.endswith("/N") else s.unit
    spec = {"m": 8, "m/s": 11, "m/s^2": 12}.get(base, 0)
    real = not np.any(s.values.imag)
    v = s.values.real if real else s.values
    common = dict(id1=s.name, id2=id2, id3=id3, id4=f"odsplat {s.kind} unit={s.unit or 'NONE'}", model_type=1,
                  data_ch=2, spec_data_type=spec, node_nums=s.node_ids, load_case=1, r1=v[:, 0], r2=v[:, 1],
                  r3=v[:, 2])
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
              frfs: Sequence[FRFRecord] = (), shapes: Sequence[ShapeRecord] = (), description: str = "") -> Path:
    """Write the records to one ASCII universal file (atomically: a failure leaves no partial file)."""
    path = Path(path)
    time_series, frfs, shapes = list(time_series), list(frfs), list(shapes)
    _check_records(geometry, time_series, frfs, shapes)
    if geometry is None and not (time_series or frfs or shapes):
        raise InputError(path, "nothing to write: no geometry, time series, FRFs or shapes")
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
    numbers = {"mode": 0, "ods": 0}
    for s in shapes:
        numbers[s.kind] += 1
        sets.append((f"shape {s.name!r}", _shape_dset(s, numbers[s.kind], id2, id3)))
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


def _from_58(d: dict, i: int, taken: set[str]) -> TimeSeries | FRFRecord:
    ft, src = int(d["func_type"]), f"dataset #{i} (58, {_label(d.get('id1')) or 'unnamed'})"
    if ft not in (1, 4):
        raise InputError(src, f"function type {ft} is neither a time response (1) nor an FRF (4)")
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
    name = _unique(_label(d.get("id1")) or _label(d.get("rsp_ent_name")), f"{'time' if ft == 1 else 'frf'} {i}", taken)
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
    tag = _UNIT_TAG.search(_label(d.get("id4")))
    unit = _label(tag.group(1)) if tag else {8: "m", 11: "m/s", 12: "m/s^2"}.get(int(d["spec_data_type"]), "")
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
    return ShapeRecord(name, freq, damping, np.asarray(d["node_nums"]).astype(np.int64), values, kind, unit)


def read_uff(path: str | Path) -> ResultSet:
    """Read nodes (2411 or 15), trace lines (82), time responses and FRFs (58, 58b) and shapes (55) from a
    universal file. Datasets of other kinds, or that do not fit the records, are listed in `skipped`."""
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
            {TimeSeries: out.time_series, FRFRecord: out.frfs, ShapeRecord: out.shapes}[type(rec)].append(rec)
    if nodes:
        ids, coords = np.concatenate([n[0] for n in nodes]), np.concatenate([n[1] for n in nodes]) / length_factor
        known = set(ids.tolist())
        try:
            out.geometry = Geometry(ids, coords, [ln for ln in lines if set(ln) <= known] if lines else None)
        except InputError as exc:
            raise InputError(path, f"nodes (2411/15): {exc.problem}") from exc
    if out.geometry is None and not (out.time_series or out.frfs or out.shapes):
        raise InputError(path, f"holds no nodes, functions (58) or shapes (55) odsplat can read; dataset types "
                               f"{sorted(set(types))}" + (f"; skipped: {out.skipped[:3]}" if out.skipped else ""))
    return out


# ------------------------------------------------------------------------------------------------------- HDF5

_H5_GROUPS = (("time_series", TimeSeries), ("frfs", FRFRecord), ("shapes", ShapeRecord))
_RESERVED = ("kind", "schema_version", "created_utc", "json_attrs")


def _plain(value: Any) -> Any:
    """An HDF5 attribute as Python: str, int, float, or a direction vector as a tuple."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return tuple(float(c) for c in value)
    return value.item() if isinstance(value, np.generic) else value


def write_results_h5(path: str | Path, *, geometry: Geometry | None = None, time_series: Sequence[TimeSeries] = (),
                     frfs: Sequence[FRFRecord] = (), shapes: Sequence[ShapeRecord] = (),
                     attrs: dict[str, Any] | None = None) -> Path:
    """Write the records to an HDF5 file in the layout of the module docstring (atomically)."""
    path = Path(path)
    records = {"time_series": list(time_series), "frfs": list(frfs), "shapes": list(shapes)}
    attrs = dict(attrs or {})
    _check_records(geometry, *records.values())
    if set(_RESERVED) & set(attrs):
        raise InputError("attrs", f"{sorted(set(_RESERVED) & set(attrs))} are reserved by the results layout")
    json_keys = [k for k, v in attrs.items() if v is None or isinstance(v, (dict, list, tuple))]
    with atomic_path(path) as tmp, h5py.File(tmp, "w", track_order=True) as f:
        f.attrs.update({"kind": RESULTS_KIND, "schema_version": RESULTS_SCHEMA, "json_attrs": json.dumps(json_keys),
                        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds")})
        f.attrs.update({k: json.dumps(v) if k in json_keys else v for k, v in attrs.items()})
        if geometry is not None:
            g = f.create_group("geometry", track_order=True)
            g.create_dataset("node_ids", data=geometry.node_ids)
            g.create_dataset("coords_m", data=geometry.coords_m).attrs["unit"] = "m"
            if geometry.lines is not None:
                g.create_dataset("lines", data=np.asarray(geometry.lines, np.int64).reshape(-1, 2))
            if geometry.names is not None:
                g.create_dataset("names", data=list(geometry.names), dtype=h5py.string_dtype())
        for group, recs in records.items():
            parent = f.create_group(group, track_order=True) if recs else None
            for r in recs:
                g = parent.create_group(r.name, track_order=True)
                for fld in fields(r):
                    value = getattr(r, fld.name)
                    if isinstance(value, np.ndarray):
                        g.create_dataset(fld.name, data=value)
                    elif fld.name != "name":
                        g.attrs[fld.name] = np.asarray(value, float) if isinstance(value, tuple) else value
    return path


def read_results_h5(path: str | Path) -> ResultSet:
    """Read a file written by `write_results_h5`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise InputError(path, f"not an HDF5 file ({exc})") from exc
    with f:
        if _plain(f.attrs.get("kind")) != RESULTS_KIND:
            raise InputError(path, f"not an {RESULTS_KIND} file (kind={_plain(f.attrs.get('kind'))!r})")
        version = _plain(f.attrs.get("schema_version"))
        if version != RESULTS_SCHEMA:
            raise SchemaError(path, f"results schema {version}; this odsplat reads {RESULTS_SCHEMA}")
        json_keys = json.loads(_plain(f.attrs.get("json_attrs", "[]")))
        out = ResultSet(attrs={k: json.loads(v) if k in json_keys else _plain(v) for k, v in f.attrs.items()
                               if k not in _RESERVED})
        try:
            if "geometry" in f:
                g = f["geometry"]
                lines = [(int(a), int(b)) for a, b in g["lines"][()]] if "lines" in g else None
                names = [_plain(s) for s in g["names"][()]] if "names" in g else None
                out.geometry = Geometry(g["node_ids"][()], g["coords_m"][()], lines, names)
            for group, cls in _H5_GROUPS:
                for name, g in f.get(group, {}).items():
                    kw = {fld.name: g[fld.name][()] if fld.name in g else _plain(g.attrs[fld.name])
                          for fld in fields(cls) if fld.name != "name"}
                    getattr(out, group).append(cls(name=name, **kw))
        except KeyError as exc:
            raise InputError(path, f"incomplete results file: {exc}") from exc
    return out
