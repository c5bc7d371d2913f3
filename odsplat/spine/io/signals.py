"""Read uniformly sampled DAQ signals (CSV, LabVIEW .lvm, universal file 58/58b) into SI channels."""
from __future__ import annotations

import functools
import io
import itertools
import logging
import math
import os
import re
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator, NamedTuple, Sequence

import numpy as np
import pyuff

from odsplat.spine.errors import InputError
from odsplat.spine.io.limits import check_sample_rate
from odsplat.spine.manifest import check_regular_file
from odsplat.spine.units import parse_unit

log = logging.getLogger(__name__)

# A step that strays further than this from the mean step means the file is not uniformly sampled.
_STEP_TOLERANCE = 1e-3


@dataclass(frozen=True)
class SignalChannel:
    """One measured quantity, converted to SI."""

    name: str
    unit: str  # SI unit name from odsplat.spine.units, e.g. "N", "m/s^2"
    values: np.ndarray  # float32, shape (N,), in `unit`
    source_unit: str  # the unit as spelled in the file (or given by the caller), e.g. "g", "Newtons"


@dataclass(frozen=True)
class SignalSet:
    """Channels that share one sample clock: sample k of every channel was taken at t0_s + k / sample_rate_hz."""

    path: Path
    sample_rate_hz: float
    t0_s: float  # time of sample 0 in the file's own time base
    channels: tuple[SignalChannel, ...]

    def __post_init__(self) -> None:
        lengths = {c.name: c.values.shape[0] for c in self.channels}
        if len(set(lengths.values())) > 1:
            raise InputError(self.path, f"channels differ in length: {lengths}")

    @property
    def n_samples(self) -> int:
        return self.channels[0].values.shape[0] if self.channels else 0

    def channel(self, name: str) -> SignalChannel:
        for channel in self.channels:
            if channel.name == name:
                return channel
        raise InputError(self.path, f"no channel {name!r}; channels are {[c.name for c in self.channels]}")


class _RawChannel(NamedTuple):
    name: str
    unit: str | None  # as spelled in the file; None or "" when the file gives none
    values: np.ndarray  # float64, file units


class _Raw(NamedTuple):
    sample_rate_hz: float
    t0_s: float
    channels: list[_RawChannel]
    clock: str  # the file's fields the rate and t0 come from, for errors: "Delta_X, X0"


def read_signals(
    path: str | os.PathLike,
    *,
    units: dict[str, str] | None = None,
    columns: Sequence[str] | None = None,
    time_column: str | None = None,
    sample_rate_hz: float | None = None,
) -> SignalSet:
    """Read a signal file, choosing the format by suffix (.csv/.txt, .lvm, .uff/.unv).

    `units` maps channel name -> unit spelling, overriding or supplying the file's; `columns` selects
    and orders channels. Every value is converted to SI and stored as float32. A CSV's time column is the first
    one with a common time name, or `time_column`; a CSV without one needs `sample_rate_hz`. A declared
    `sample_rate_hz` is used as the rate (the time stamps' printed rounding does not enter it); a file whose own
    rate disagrees with it by more than RATE_AGREEMENT is refused.
    """
    path = Path(path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None:
        raise InputError(path, f"unsupported suffix {path.suffix!r}; expected one of {', '.join(_READERS)}")
    check_regular_file(path, "signal file")
    if sample_rate_hz is not None:
        check_sample_rate(sample_rate_hz, f"{path}: sample_rate_hz")
    if reader is _read_csv:
        raw = _read_csv(path, time_column=time_column, sample_rate_hz=sample_rate_hz)
    elif time_column is not None:
        raise InputError(f"{path}: time_column", f"a {path.suffix} file's time axis is in its header; "
                                                 "time_column is for CSV files")
    else:
        raw = reader(path)
    check_sample_rate(raw.sample_rate_hz, f"{path}: {raw.clock}")
    if not math.isfinite(raw.t0_s):
        raise InputError(f"{path}: {raw.clock}", f"the first sample's time is {raw.t0_s}, not a finite number")
    n_samples = min((len(c.values) for c in raw.channels), default=0)
    if n_samples < 2:
        raise InputError(path, f"holds {n_samples} sample(s); a signal needs at least 2")
    if sample_rate_hz is not None:
        if abs(raw.sample_rate_hz - sample_rate_hz) > RATE_AGREEMENT * sample_rate_hz:
            raise InputError(f"{path}: sample_rate_hz", f"the file's time axis gives {raw.sample_rate_hz:.10g} Hz, "
                                                        f"not the {sample_rate_hz:g} Hz declared")
        raw = raw._replace(sample_rate_hz=float(sample_rate_hz))
    signals = _assemble(path, raw, units or {}, columns)
    log.debug("read %s: %d channels x %d samples at %g Hz", path, len(signals.channels), signals.n_samples,
              signals.sample_rate_hz)
    return signals


def _assemble(path: Path, raw: _Raw, units: dict[str, str], columns: Sequence[str] | None) -> SignalSet:
    """Select channels, resolve their units and convert them to SI float32."""
    by_name = {c.name: c for c in raw.channels}
    names = [c.name for c in raw.channels]
    repeated = [name for name, count in Counter(names).items() if count > 1]
    if repeated:
        raise InputError(path, f"more than one channel is named {repeated[0]!r}")
    unknown = sorted(set(units) - set(names))
    if unknown:
        raise InputError(path, f"units given for {unknown}, which are not channels of this file {names}")
    if columns is not None:
        for name in columns:
            if name not in by_name:
                raise InputError(path, f"no column {name!r}; the file has {names}")
        if len(set(columns)) != len(columns) or not columns:
            raise InputError(path, f"columns must name each channel at most once and at least one: {list(columns)}")
        names = list(columns)
    channels = []
    for name in names:
        spelled = units.get(name, by_name[name].unit)
        # parse_unit reads "" as dimensionless, but a blank unit in a file means nobody said.
        if not spelled:
            raise InputError(path, f"channel {name!r} has no unit; give one with units={{{name!r}: ...}}")
        si_unit, scale = _parse_unit(path, name, spelled)
        with np.errstate(over="ignore", invalid="ignore"):
            values = (by_name[name].values * scale).astype(np.float32)
        _check_finite(path, name, by_name[name].values, values, spelled, si_unit)
        values.flags.writeable = False
        channels.append(SignalChannel(name=name, unit=si_unit, values=values, source_unit=spelled))
    # 1/dt of a printed dt carries float noise (1/2e-5 = 49999.99999999999); 10 digits drop it.
    rate = float(f"{raw.sample_rate_hz:.10g}")
    return SignalSet(path=path, sample_rate_hz=rate, t0_s=raw.t0_s, channels=tuple(channels))


def _check_finite(path: Path, name: str, raw: np.ndarray, values: np.ndarray, spelled: str, si_unit: str) -> None:
    """Every format's samples, once converted: a NaN or inf in the file, or a value float32 cannot hold in SI."""
    bad = ~np.isfinite(values)
    if bad.any():
        k = int(np.argmax(bad))
        why = "not a finite number" if not np.isfinite(raw[k]) else f"beyond float32 once converted to {si_unit}"
        raise InputError(path, f"column {name!r}: sample {k} is {raw[k]:g} {spelled}, {why}")


def _parse_unit(path: Path, column: str, spelled: str) -> tuple[str, float]:
    """parse_unit, with the error naming the file and the column."""
    try:
        return parse_unit(spelled, where=str(path))
    except InputError as exc:
        raise InputError(path, f"column {column!r}: {exc.problem}") from None


def _first_bad_cell(rows: Iterable[tuple[int, str]], sep: str, cols: Sequence[int], names: Sequence[str]) -> str | None:
    """Say where the first missing, non-numeric or non-finite cell is; the slow path, run only after numpy refused."""
    for line_no, line in rows:
        fields = line.split(sep)
        if len(fields) <= max(cols):
            missing = next(name for col, name in zip(cols, names) if col >= len(fields))
            return f"line {line_no} has {len(fields)} fields; column {missing!r} is missing"
        for col, name in zip(cols, names):
            cell = fields[col].strip()
            if not cell:
                return f"line {line_no}: empty cell in column {name!r}"
            try:
                value = float(cell)
            except ValueError:
                return f"line {line_no}: column {name!r} holds {cell!r}, not a number"
            if not math.isfinite(value):
                return f"line {line_no}: column {name!r} holds {cell!r}, not a finite number"
    return None


def _load_table(path: Path, source: io.TextIOBase, sep: str, cols: Sequence[int], names: Sequence[str],
                rows: Callable[[], Iterable[tuple[int, str]]], comments: str | None, n_fields: int) -> np.ndarray:
    """Parse numeric columns in bulk with numpy; on any fault, find and name the offending line and column. A row
    of more than `n_fields` fields (trailing separators aside) is ragged: numpy would drop its extra cells."""
    try:
        with warnings.catch_warnings():  # "input contained no data": the caller says so in its own words
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(source, delimiter=sep, usecols=cols, ndmin=2, comments=comments, dtype=np.float64)
    except ValueError as exc:
        raise InputError(path, _first_bad_cell(rows(), sep, cols, names) or str(exc)) from None
    if not np.isfinite(table).all():
        raise InputError(path, _first_bad_cell(rows(), sep, cols, names) or "non-finite value")
    for line_no, line in rows():
        fields = line.rstrip().rstrip(sep).count(sep) + 1
        if fields > n_fields:
            raise InputError(path, f"line {line_no} has {fields} fields, more than the {n_fields} columns of the "
                                   "heading: a ragged row")
    return table


# --- CSV -------------------------------------------------------------------------------------------------

_HEADING = re.compile(r"^(?P<name>.*?)\s*(?:\[(?P<bracket>[^\]]*)\]|\((?P<paren>[^)]*)\))?$")


TIME_NAMES = ("time", "t", "times", "timestamp", "elapsed")   # a time column's names, in any case
_TIME_SUFFIXES = ("s", "sec", "ms", "us", "µs")                # time_s, t_ms, ...


def _time_unit(name: str, unit: str | None) -> str | None | bool:
    """The unit of a time column's heading (None: none given, seconds), or False when the heading is no time:
    'time', 'Time [ms]', 't (s)', 'timestamp', 'time_s', 't_ms'."""
    n = name.strip().lower()
    if n in TIME_NAMES:
        return unit
    base, sep, suffix = n.rpartition("_")
    if sep and base in TIME_NAMES and suffix in _TIME_SUFFIXES and unit is None:
        return suffix
    return False


def _split_heading(heading: str) -> tuple[str, str | None]:
    """'force [N]' or 'acc1 (g)' -> (name, unit); a heading without brackets has no unit."""
    match = _HEADING.match(heading.strip().strip('"').strip())
    unit = match["bracket"] if match["bracket"] is not None else match["paren"]
    return match["name"], None if unit is None else unit.strip()


def _csv_rows(path: Path, header_no: int) -> Iterator[tuple[int, str]]:
    """(line number, text) of each data row, skipping comments and blank lines as np.loadtxt does."""
    with path.open(encoding="utf-8-sig", errors="replace") as f:
        for line_no, line in enumerate(f, 1):
            text = line.split("#", 1)[0]
            if line_no > header_no and text.strip():
                yield line_no, text.rstrip("\n")


def _csv_line(path: Path, header_no: int, row: int) -> int:
    """File line number of data row `row` (counted from 0), for error messages."""
    return next(itertools.islice(_csv_rows(path, header_no), row, None))[0]


def _print_resolution(t: np.ndarray) -> np.ndarray:
    """Each value's printed resolution, the larger of two readings: the decimal step of the column (1e-6 for
    '0.000333'), and one unit of each value's last digit when all were printed to n significant digits
    ('0.1000000', '4.882812e-05'; the decimal step alone reads these as 1e-12). 0 where finer than both tell."""
    fixed = 0.0
    for digits in range(13):
        scaled = t * 10.0**digits
        if np.all(np.abs(scaled - np.rint(scaled)) < 1e-3):
            fixed = 10.0**-digits
            break
    significant = np.zeros(t.shape)
    magnitude = np.floor(np.log10(np.where(t == 0, 1.0, np.abs(t))))
    for n in range(1, 16):
        unit = 10.0 ** (magnitude - n + 1)
        scaled = t / unit
        if np.all(np.abs(scaled - np.rint(scaled)) < 1e-3):
            significant = unit
            break
    return np.maximum(fixed, significant)


RATE_AGREEMENT = 1e-4   # a declared rate and a file's time axis agree to this (relative): printed rounding only


def _time_index(path: Path, parsed: list[tuple[str, str | None]], time_column: str | None,
                declared: bool) -> int | None:
    """Which column is time: the one named `time_column`, else the first if it has a time name; None when there
    is none and the rate is declared."""
    if time_column is not None:
        want = time_column.strip().lower()
        hits = [i for i, (name, unit) in enumerate(parsed)
                if name.strip().lower() == want or f"{name} [{unit}]".lower() == want]
        if not hits:
            raise InputError(f"{path}: time_column", f"no column {time_column!r}; the columns are "
                                                     f"{[name for name, _ in parsed]}")
        return hits[0]
    if _time_unit(*parsed[0]) is not False:
        return 0
    if declared:
        return None
    raise InputError(path, f"first column must be time ({', '.join(map(repr, TIME_NAMES))}, with its unit in "
                           f"brackets or as a suffix such as 'time_s' or 't_ms'), not {parsed[0][0]!r}; or name it "
                           "with time_column, or declare sample_rate_hz, in the rig's take")


def _read_csv(path: Path, *, time_column: str | None = None, sample_rate_hz: float | None = None) -> _Raw:
    # utf-8-sig: spreadsheet programs start UTF-8 CSV with a byte-order mark.
    with path.open(encoding="utf-8-sig", errors="replace") as f:
        header_no, header = 0, ""
        while not header:
            line = f.readline()
            if not line:
                raise InputError(path, "no header row")
            header_no += 1
            header = "" if line.lstrip().startswith("#") else line.strip()
        sep = max([",", ";", "\t"], key=header.count)
        headings = header.split(sep)
        if headings[-1].strip() == "":  # a trailing delimiter, as some exporters write
            headings.pop()
        parsed = [_split_heading(h) for h in headings]
        ti = _time_index(path, parsed, time_column, sample_rate_hz is not None) if headings else None
        if len(headings) < 2 - (ti is None):
            raise InputError(path, f"header {header!r} needs a time column and at least one channel, "
                                   "separated by ',', ';' or tab")
        names = [name for name, _ in parsed]
        rows = functools.partial(_csv_rows, path, header_no)
        table = _load_table(path, f, sep, range(len(names)), names, rows, "#", len(headings))
    if table.shape[0] < 2:
        raise InputError(path, f"only {table.shape[0]} data row(s); a signal needs at least 2")
    if ti is None:   # no time column: sample k at k / the declared rate
        channels = [_RawChannel(name, unit, table[:, i]) for i, (name, unit) in enumerate(parsed)]
        return _Raw(float(sample_rate_hz), 0.0, channels, "sample_rate_hz")

    time_unit = _time_unit(*parsed[ti])
    time_unit = parsed[ti][1] if time_unit is False else time_unit   # named by time_column: its unit, or s
    time_si, time_scale = _parse_unit(path, headings[ti], time_unit or "s")
    if time_si != "s":
        raise InputError(path, f"time column {headings[ti]!r} has unit {time_unit!r}, not a unit of time")

    t = table[:, ti]
    step = np.diff(t)
    if (step <= 0).any():
        row = int(np.argmax(step <= 0)) + 1
        raise InputError(path, f"time does not increase at line {_csv_line(path, header_no, row)} "
                               f"({t[row]:g} after {t[row - 1]:g})")
    # The mean step over the whole record: far less hurt by the printed rounding than any single step.
    mean_step = (t[-1] - t[0]) / (len(t) - 1)
    # Rounding when the time was printed moves a step by up to one printed digit; allow that, but never
    # half a sample, which would let a dropped sample through.
    res = _print_resolution(t)
    tolerance = _STEP_TOLERANCE * mean_step + np.minimum(np.maximum(res[1:], res[:-1]), mean_step / 2)
    off = np.abs(step - mean_step) > tolerance
    if off.any():
        row = int(np.argmax(off)) + 1
        unit = time_unit or "s"
        raise InputError(path, f"time step at line {_csv_line(path, header_no, row)} is {step[row - 1]:g} {unit}, "
                               f"not the mean {mean_step:g} {unit}: the file is not uniformly sampled")
    channels = [_RawChannel(name, unit, table[:, i]) for i, (name, unit) in enumerate(parsed) if i != ti]
    return _Raw(1.0 / (mean_step * time_scale), float(t[0] * time_scale), channels, f"time column {headings[ti]!r}")


# --- LabVIEW .lvm -----------------------------------------------------------------------------------------

_LVM_END = "***End_of_Header***"
_LVM_SEPARATORS = {"Tab": "\t", "Comma": ","}


class _LvmSegment(NamedTuple):
    names: list[str]
    units: list[str]
    delta_x: float
    x0: float
    table: np.ndarray


def _after_line(text: str, pos: int) -> int:
    """Index of the line after the one holding `pos`; len(text) on the last line."""
    newline = text.find("\n", pos)
    return len(text) if newline < 0 else newline + 1


def _lvm_tags(block: str, sep: str) -> dict[str, list[str]]:
    """Tag -> the fields of its row, tag at index 0, so field i lines up with column i of the data."""
    tags = {}
    for line in block.splitlines():
        fields = [field.strip() for field in line.split(sep)]
        if fields[0]:
            tags[fields[0]] = fields
    return tags


def _lvm_value(fields: list[str], col: int) -> str:
    # A row too short to reach this column holds one value for all channels (Multi_Headings No).
    return fields[col] if col < len(fields) else fields[1]


def _read_lvm(path: Path) -> _Raw:
    raw_bytes = path.read_bytes()
    try:
        text = raw_bytes.decode("utf-8")
    except UnicodeDecodeError:  # LabVIEW on Windows writes the ANSI code page
        text = raw_bytes.decode("cp1252", errors="replace")
    del raw_bytes  # a 100 MB file need not be held twice
    if not text.startswith("LabVIEW Measurement"):
        raise InputError(path, "not a LabVIEW measurement file: it does not start with 'LabVIEW Measurement'")
    end = text.find(_LVM_END)
    if end < 0:
        raise InputError(path, f"no {_LVM_END} line")
    # The header itself is written with the separator it announces, so find that first.
    match = re.search(r"^Separator[\t,](\w+)", text[:end], re.M)
    sep = _LVM_SEPARATORS.get(match[1] if match else "Tab")
    if sep is None:
        raise InputError(path, f"unknown Separator {match[1]!r}; expected Tab or Comma")
    file_tags = _lvm_tags(text[:end], sep)
    decimal = file_tags.get("Decimal_Separator", ["", "."])[1] or "."
    if decimal == sep:
        raise InputError(path, "the decimal separator is also the column separator")

    segments = []
    pos = _after_line(text, end)
    while (end := text.find(_LVM_END, pos)) >= 0:
        body = _after_line(text, end)
        following = text.find("\nChannels" + sep, body)
        stop = len(text) if following < 0 else following + 1
        segments.append(_lvm_segment(path, text, pos, body, stop, sep, decimal, len(segments) + 1))
        pos = stop
    if not segments:
        raise InputError(path, "no segment header (Channels, Delta_X, ...) after the file header")

    first = segments[0]
    x_end = first.x0
    for k, seg in enumerate(segments, 1):
        same_channels = (seg.names, seg.units) == (first.names, first.units)
        if not same_channels or not math.isclose(seg.delta_x, first.delta_x, rel_tol=1e-9):
            raise InputError(path, f"segment {k} has channels {seg.names} in {seg.units} at Delta_X {seg.delta_x:g}, "
                                   f"segment 1 has {first.names} in {first.units} at {first.delta_x:g}")
        # Concatenating is only honest when each segment starts where the last one stopped.
        if abs(seg.x0 - x_end) > first.delta_x / 2:
            raise InputError(path, f"segment {k} starts at X0 = {seg.x0:g}, not at {x_end:g} where segment "
                                   f"{k - 1} ends; the segments are not one continuous record")
        x_end = seg.x0 + seg.table.shape[0] * seg.delta_x
    table = np.concatenate([seg.table for seg in segments]) if len(segments) > 1 else first.table
    channels = [_RawChannel(name, unit, table[:, i]) for i, (name, unit) in enumerate(zip(first.names, first.units))]
    return _Raw(1.0 / first.delta_x, first.x0, channels, "Delta_X, X0")


def _lvm_segment(path: Path, text: str, start: int, body: int, stop: int, sep: str, decimal: str,
                 number: int) -> _LvmSegment:
    """Parse one segment: its header in text[start:body], its column-name row and data in text[body:stop]."""
    where = f"segment {number}"
    tags = _lvm_tags(text[start:body], sep)
    name_row, _, data = text[body:stop].partition("\n")
    headings = [h.strip() for h in name_row.split(sep)]
    if headings[0] != "X_Value":
        raise InputError(path, f"{where}: expected the column-name row (X_Value ...), found {name_row[:60]!r}")
    # X columns (X_Columns One or Multi) and the trailing Comment column carry no channel data.
    cols = [i for i, h in enumerate(headings) if h != "X_Value" and not (h == "Comment" and i == len(headings) - 1)]
    names = [headings[i] for i in cols]
    n_channels = tags.get("Channels", ["", str(len(cols))])[1]
    if n_channels != str(len(cols)):
        raise InputError(path, f"{where}: header says {n_channels} channels but the columns are {names}")
    for tag in ("X0", "Delta_X"):
        if tag not in tags:
            raise InputError(path, f"{where}: no {tag} in the segment header")

    def numbers(tag: str) -> list[float]:
        try:
            values = [float(_lvm_value(tags[tag], i).replace(decimal, ".")) for i in cols]
        except ValueError:
            values = [math.nan]
        if not all(map(math.isfinite, values)):
            raise InputError(path, f"{where}: {tag} {tags[tag][1:]} is not a finite number per channel")
        return values

    delta_x, x0 = numbers("Delta_X"), numbers("X0")
    if max(delta_x) - min(delta_x) > 1e-9 * max(delta_x) or max(x0) - min(x0) > 1e-3 * delta_x[0]:
        raise InputError(path, f"{where}: channels differ in Delta_X {delta_x} or X0 {x0}; "
                               "only one shared sample clock is supported")
    if delta_x[0] <= 0:
        raise InputError(path, f"{where}: Delta_X is {delta_x[0]:g}, it must be positive")
    dims = {_lvm_value(tags["X_Dimension"], i) for i in cols} if "X_Dimension" in tags else {"Time"}
    if dims != {"Time"}:
        raise InputError(path, f"{where}: X_Dimension is {sorted(dims)}; only time series are read")
    units = [_lvm_value(tags["Y_Unit_Label"], i) for i in cols] if "Y_Unit_Label" in tags else [""] * len(cols)

    first_line = text.count("\n", 0, body) + 2
    # Separators written between segments (a lone tab) must not read as a short data row.
    data = data.rstrip()
    if decimal != ".":  # bulk replace: a decimal comma is the only comma a tab-separated number can hold
        data = data.replace(decimal, ".")

    def rows() -> Iterator[tuple[int, str]]:
        return ((first_line + i, line) for i, line in enumerate(data.split("\n")) if line.strip())

    table = _load_table(path, io.StringIO(data), sep, cols, names, rows, None, len(headings))
    samples = [_lvm_value(tags["Samples"], i) for i in cols] if "Samples" in tags else []
    if any(not n.isdigit() for n in samples):
        raise InputError(path, f"{where}: Samples {tags['Samples'][1:]} is not a count per channel")
    declared = max(map(int, samples), default=0)
    if table.shape[0] < declared:
        raise InputError(path, f"{where}: truncated: {table.shape[0]} rows, but its header declares {declared} "
                               "Samples")
    if declared and table.shape[0] > declared:
        # LabVIEW's "one header only" mode keeps appending rows under the first write's Samples count.
        log.debug("%s %s: header says %d samples, found %d rows", path, where, declared, table.shape[0])
    return _LvmSegment(names, units, delta_x[0], x0[0], table)


# --- Universal file, dataset 58 / 58b --------------------------------------------------------------------

_UFF_TIME_RESPONSE = 1  # function type of a time series
_UFF_REAL_ORDINATES = (2, 4)  # real single and real double precision
_UFF_BLANK = ("", "NONE")


def _uff_names(records: list[dict]) -> list[str]:
    """id1 where it is given and unique, else rsp_node{N}_dir{D}; any remaining clash gets a numeric suffix."""
    ids = [str(r.get("id1", "")).strip() for r in records]
    id_counts = Counter(ids)
    names = [i if i not in _UFF_BLANK and id_counts[i] == 1 else f"rsp_node{r['rsp_node']}_dir{r['rsp_dir']}"
             for i, r in zip(ids, records)]
    counts, seen = Counter(names), Counter()
    unique = []
    for name in names:
        seen[name] += 1
        unique.append(f"{name}_{seen[name]}" if counts[name] > 1 else name)
    return unique


def _read_uff(path: Path) -> _Raw:
    try:
        uff = pyuff.UFF(str(path))
        kinds = [int(kind) for kind in uff.get_set_types()]
        indices = [i for i, kind in enumerate(kinds) if kind == 58]
        records = [uff.read_sets(i) for i in indices]
    except Exception as exc:  # pyuff raises bare Exception (and worse) on damaged files
        raise InputError(path, f"cannot read as a universal file: {exc}") from exc

    usable = []
    for index, record in zip(indices, records):
        if (record.get("func_type") == _UFF_TIME_RESPONSE and record.get("ord_data_type") in _UFF_REAL_ORDINATES
                and record.get("abscissa_spacing") == 1 and record.get("abscissa_inc", 0) > 0):
            usable.append(record)
        else:
            log.debug("%s: skipping dataset %d (function type %s, ordinate type %s, abscissa spacing %s): "
                      "not an evenly spaced real time series", path, index, record.get("func_type"),
                      record.get("ord_data_type"), record.get("abscissa_spacing"))
    if not usable:
        raise InputError(path, f"no evenly spaced real time series (dataset 58, function type 1); the file holds "
                               f"dataset types {sorted(set(kinds))}, dataset-58 function types "
                               f"{sorted({r.get('func_type') for r in records})}")

    for record in usable:
        # pyuff keeps the values it finds: a cut file or a misaligned line gives fewer (or more) without a word.
        if record.get("num_pts") != len(record["data"]):
            raise InputError(path, f"time record {str(record.get('id1', '')).strip()!r} holds {len(record['data'])} "
                                   f"values, but its header (num_pts) declares {record.get('num_pts')}")
    names = _uff_names(usable)
    clocks = {(r["abscissa_inc"], r["abscissa_min"], len(r["data"])) for r in usable}
    if len(clocks) > 1:
        described = "; ".join(f"{n}: dt {r['abscissa_inc']:g} s, t0 {r['abscissa_min']:g} s, {len(r['data'])} samples"
                              for n, r in zip(names, usable))
        raise InputError(path, f"time records do not share one sample clock ({described})")
    units = [str(r.get("ordinate_axis_units_lab", "")).strip() for r in usable]
    channels = [_RawChannel(name, None if unit in _UFF_BLANK else unit, np.asarray(r["data"], dtype=np.float64))
                for name, unit, r in zip(names, units, usable)]
    return _Raw(1.0 / usable[0]["abscissa_inc"], float(usable[0]["abscissa_min"]), channels,
                "abscissa_inc, abscissa_min")


_READERS: dict[str, Callable[[Path], _Raw]] = {
    ".csv": _read_csv, ".txt": _read_csv, ".lvm": _read_lvm, ".uff": _read_uff, ".unv": _read_uff,
}
