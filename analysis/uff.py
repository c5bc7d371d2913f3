"""UFF (`write_uff` / `read_uff`, through pyuff): 151 header and 164 units (SI: metre, newton, second), 2411 nodes
(metres), 82 trace lines, 58 functions (function type 1 time response, 4 FRF, 6 coherence; double precision,
complex FRFs, real coherence), 55 shapes (3-DOF translation vectors; real modes as analysis type 2 with frequency
and viscous damping ratio, complex modes as type 3 with the eigenvalue -zeta*wn + i*wn*sqrt(1-zeta^2) in rad/s,
ODS as type 5 at a frequency line). Headers hold 6 significant digits (E13.5): abscissa start and step,
frequencies, dampings and all of dataset 55; ordinates of 58 hold 12. ID line 1 is the record's name; an
`odsplat ... unit=U set=S` tag in ID line 4 of a 55 keeps its unit and shape set, and a direction given as a
vector is kept in ID line 5 (`rsp=(x,y,z)`). A 55's shape set is its load case (1, 2, ... in the order the sets
first appear), its number the mode number (modes) or frequency step number (ODS), counted within its set and
kind unless the record gives one: two sets may each hold a mode 3 (the same pole seen by two instruments).
"""
from __future__ import annotations

import logging
import re
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyuff

from odsplat.spine.atomic import atomic_path
from odsplat.spine.errors import InputError, OdsplatError

from .export import (
    _DIR_CODE,
    _FRF_NUMERATOR,
    _QUANTITY,
    CoherenceRecord,
    Direction,
    FRFRecord,
    Geometry,
    ResultSet,
    ShapeRecord,
    TimeSeries,
    _check_records,
    _shape_numbers,
)

log = logging.getLogger(__name__)

_CODE_DIR = {v: k for k, v in _DIR_CODE.items()}
_MONTHS = ("Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec")
_SET_TAG = re.compile(r"\bodsplat\b.*\bset=(\S+)")
_SPEC_QUANTITY = {8: "displacement", 11: "velocity", 12: "acceleration", 13: "force", 9: "force",
                  15: "pressure", 21: "pressure"}  # 21: Test.Lab's sound pressure
_UNIT_TAG = re.compile(r"\bodsplat\b.*\bunit=(\S+)")
_VECTOR_TAG = re.compile(r"\b(rsp|ref)=\(([^)]*)\)")




def _code(direction: Direction) -> int:
    if isinstance(direction, str):
        return _DIR_CODE[direction]
    i = int(np.argmax(np.abs(direction)))  # the nearest axis; the vector itself goes to ID line 5
    return (i + 1) * (1 if direction[i] > 0 else -1)


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
