"""HDF5 layout (`write_results_h5` / `read_results_h5`), groups kept in the order written::

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
from collections.abc import Sequence
from dataclasses import MISSING, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from odsplat.spine.atomic import atomic_path
from odsplat.spine.contract import CAPTURE_KEY, check_capture
from odsplat.spine.errors import InputError, OdsplatError, SchemaError
from odsplat.spine.space import writing_h5

from . import export as rec  # the records, written and read here

log = logging.getLogger(__name__)

RESULTS_KIND = "odsplat.results"
RESULTS_SCHEMA = 3
READABLE_SCHEMAS = (2, 3)


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


def write_results_h5(path: str | Path, *, geometry: rec.Geometry | None = None,
                     time_series: Sequence[rec.TimeSeries] = (), frfs: Sequence[rec.FRFRecord] = (),
                     shapes: Sequence[rec.ShapeRecord] = (), coherence: Sequence[rec.CoherenceRecord] = (),
                     mac: Sequence[rec.MACRecord] = (), stabilisation: Sequence[rec.StabilisationRecord] = (),
                     attrs: dict[str, Any] | None = None, capture_id: str | None = None) -> Path:
    """Write the records to an HDF5 file in the layout of the module docstring (atomically); `capture_id`: the
    capture the results are of, recorded for `read_results_h5` to check."""
    path = Path(path)
    records = {"time_series": list(time_series), "frfs": list(frfs), "shapes": list(shapes),
               "coherence": list(coherence), "mac": list(mac), "stabilisation": list(stabilisation)}
    attrs = dict(attrs or {})
    rec._check_records(geometry, records)
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


def read_results_h5(path: str | Path, capture_id: str | None = None) -> rec.ResultSet:
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


def _read_results(f: h5py.File, path: Path, capture_id: str | None) -> rec.ResultSet:
    if _plain(f.attrs.get("kind")) != RESULTS_KIND:
        raise InputError(path, f"not an {RESULTS_KIND} file (kind={_plain(f.attrs.get('kind'))!r})")
    version = _plain(f.attrs.get("schema_version"))
    if version not in READABLE_SCHEMAS:
        raise SchemaError(path, f"results schema {version}; this odsplat reads "
                                f"{', '.join(str(v) for v in READABLE_SCHEMAS)}")
    check_capture(f.attrs.get(CAPTURE_KEY), path, capture_id)
    try:
        json_keys = json.loads(_plain(f.attrs.get("json_attrs", "[]")))
        out = rec.ResultSet(attrs={k: json.loads(v) if k in json_keys else _plain(v) for k, v in f.attrs.items()
                               if k not in _RESERVED})
    except (json.JSONDecodeError, TypeError) as exc:
        raise InputError(path, f"attributes: not the JSON text the results layout stores ({exc})") from None
    try:
        if "geometry" in f:
            g = f["geometry"]
            lines = [(int(a), int(b)) for a, b in g["lines"][()]] if "lines" in g else None
            names = [_plain(s) for s in g["names"][()]] if "names" in g else None
            out.geometry = rec.Geometry(g["node_ids"][()], g["coords_m"][()], lines, names)
        for group, (_, cls) in rec._KINDS.items():
            for name, g in f.get(group, {}).items():
                getattr(out, group).append(_h5_record(cls, name, g))
    except KeyError as exc:
        raise InputError(path, f"incomplete results file: {exc}") from None
    return out
