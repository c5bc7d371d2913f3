"""Fuzz `import_capture` with the real recordings in ../shared/data, mutated: truncated, header bits flipped, numeric
fields replaced by nan/inf/huge/negative/garbage, rig names and paths that try to leave the capture (issue 29).

Every input must end in one of two ways: refused with one InputError line, leaving nothing (no OUT, no temporary,
no file anywhere else), or imported. An import of an input whose corrupted field the reader does not use must hold
exactly the uncorrupted file's frames and samples; a corrupted field the reader does use is refused or, where the
value is still a sane one, imports the same frames and samples. Nothing else may escape, nothing may hang.
"""
from __future__ import annotations

import dataclasses
import faulthandler
import os
import random
import re
import shutil
import signal
import struct
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.importer import import_capture
from odsplat.spine.store import Capture

pytestmark = pytest.mark.skipif(os.name != "posix", reason="the per-input timeout uses SIGALRM")

SEED = int(os.environ.get("ODSPLAT_FUZZ_SEED", "29"))  # another seed explores other inputs
PER_BASE = int(os.environ.get("ODSPLAT_FUZZ_PER_BASE", "25"))
TIMEOUT_S = 10.0  # one import of these small files takes well under a second

# Replacements for a numeric field: never a number (must be refused where the field is used) ...
NOT_A_NUMBER = ["nan", "NaN", "inf", "-inf", "abc", "1.2.3"]
# ... numbers no recording has (refused where the field is a rate) ...
EXTREME = ["1e308", "-1e308", "1e-300", "99999999999999999999", "-99999999999999999999"]
# ... and plain numbers, which may be legal: they must be refused or give the uncorrupted frames and samples.
PLAIN = ["0", "-5", "7", "", "0x1F"]

CHANNELS = ('[[channels]]\nname = "force"\nkind = "force"\ncolumn = "{force}"\n'
            '[[channels]]\nname = "acc"\nkind = "acceleration"\ncolumn = "{acc}"\n')
LADISK_CHANNELS = CHANNELS.format(force="Force (Trigger)", acc="Acceleration (Trigger)")


@dataclass(frozen=True)
class Field:
    """A numeric field of a file (or the rig): where its text lies, and what the reader does with it."""

    label: str
    start: int
    end: int
    use: str  # "unused": ignored by the reader; "used"; "rate": a rate; "data": a sample value; "pyuff's": read by
    #           pyuff, not by us (a fixed-width field: a longer value moves the ones after it)


@dataclass
class Base:
    """A real recording (or one converted from one) with a rig that imports it, and the fields to corrupt."""

    name: str
    files: dict[str, bytes]
    rig: str
    target: str  # the file the mutations change
    fields: list[Field]
    header_bytes: int  # bit flips land in the first header_bytes of target
    binary_fields: bool = False  # fields are little-endian integers (start: offset, end: offset + size)
    counted: bool = True  # the target declares its length (a header's frame or sample count): a cut is refused
    baseline: list[np.ndarray] | None = None  # the uncorrupted import's frames and samples (None: refused)
    # the files written once, linked into each input
    pristine: dict[str, tuple[Path, bytes]] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class Case:
    base: str
    kind: str  # truncate, bitflip, field, name, path
    detail: str
    files: dict[str, bytes]
    rig: str
    expect: str  # "refused", "same" (imports the baseline's frames and samples), "refused_or_same", "any"


# ------------------------------------------------------------------ numeric fields of each format

def _cih_fields(text: str) -> list[Field]:
    used = {"Record Rate(fps)": "rate", "Total Frame": "used", "Image Width": "used", "Image Height": "used",
            "Color Bit": "used", "EffectiveBit Depth": "used", "Start Frame": "used", "Correct Trigger Frame": "used",
            "Save Step": "used", "Original Total Frame": "used"}
    fields, seen = [], set()
    for m in re.finditer(r"^([^:\r\n]+?) : (-?[0-9.]+)\r?$", text, re.M):
        if m[1] in seen:   # first value wins in a .cih: a repeated key's later values are unused
            continue
        seen.add(m[1])
        fields.append(Field(m[1], m.start(2), m.end(2), used.get(m[1], "unused")))
    return fields


def _cihx_fields(text: str) -> list[Field]:
    used = {"recordInfo/recordRate": "rate", "frameInfo/totalFrame": "used", "imageDataInfo/resolution/width": "used",
            "imageDataInfo/resolution/height": "used", "imageDataInfo/colorInfo/bit": "used",
            "imageDataInfo/effectiveBit/depth": "used", "frameInfo/startFrame": "used",
            "frameInfo/correctTriggerFrame": "used", "frameInfo/skipFrame": "used", "frameInfo/recordedFrame": "used"}
    fields, path = [], []
    begin = text.index("<cih>")
    for m in re.finditer(r"<(/?)([A-Za-z_][\w.-]*)[^>]*?(/?)>", text[begin:]):
        closing, tag, empty = m[1], m[2], m[3]
        if empty:
            continue
        if closing:
            path.pop()
            continue
        path.append(tag)
        value = re.match(r"-?[0-9.]+(?=<)", text[begin + m.end():])
        if value and len(path) > 1:
            key = "/".join(path[1:])
            # The same path repeated (a list in the XML): treated as used, since which one is read is not ours to say.
            fields.append(Field(key, begin + m.end(), begin + m.end() + value.end(), used.get(key, "unused")))
    return fields


def _lvm_fields(text: str) -> list[Field]:
    used = {"Channels": "used", "Samples": "used", "X0": "used", "Delta_X": "rate"}
    header = text[:text.index("X_Value")]
    fields = []
    for m in re.finditer(r"^(\w+)\t(-?[0-9]+(?:,[0-9]+)?(?:E[+-][0-9]+)?)\t", header, re.M):
        if m[1] in ("Date", "Time"):
            continue
        fields.append(Field(m[1], m.start(2), m.end(2), used.get(m[1], "unused")))
    return fields


def _uff_fields(text: str) -> list[Field]:
    """The fixed-width fields of records 6 and 7 of the first dataset 58 (function type, ordinate type, count,
    spacing, abscissa min and increment: used; the others pyuff's), the numbers of records 8 to 11 (pyuff's), and the
    first samples (13 characters each)."""
    lines = text.split("\n")
    offsets = [int(o) for o in np.cumsum([0] + [len(line) + 1 for line in lines])]
    layout = {7: ([5, 10, 5, 10, 11, 10, 4, 11, 10, 4], {0: "used"}),                      # record 6
              8: ([10, 10, 10, 13, 13, 13], {0: "used", 1: "used", 2: "used", 3: "used", 4: "rate"}),   # record 7
              13: ([13] * 6, {k: "data" for k in range(6)}), 14: ([13] * 6, {k: "data" for k in range(6)})}
    fields = []
    for i, (widths, uses) in layout.items():
        at = 0
        for k, width in enumerate(widths):
            if lines[i][at:at + width].strip():
                fields.append(Field(f"line {i + 1} field {k}", offsets[i] + at, offsets[i] + at + width,
                                    uses.get(k, "pyuff's")))
            at += width
    for i in range(9, 13):   # records 8 to 11: axis descriptions
        for m in re.finditer(r"-?[0-9]+", lines[i][:25]):
            fields.append(Field(f"line {i + 1}", offsets[i] + m.start(), offsets[i] + m.end(), "pyuff's"))
    return fields


def _csv_fields(text: str, rng: random.Random) -> list[Field]:
    lines = text.split("\n")
    offsets = np.cumsum([0] + [len(line) + 1 for line in lines])
    fields = []
    for i in rng.sample(range(1, len(lines) - 1), 12):
        start = int(offsets[i])
        for col, m in enumerate(re.finditer(r"[^,]+", lines[i])):
            fields.append(Field(f"line {i + 1} col {col}", start + m.start(), start + m.end(),
                                "used" if col == 0 else "data"))
    return fields


def _npy_fields(data: bytes) -> list[Field]:
    header = data[:128].decode("latin-1")
    shape = header.index("(")
    return [Field(f"shape[{k}]", shape + m.start(), shape + m.end(), "used")
            for k, m in enumerate(re.finditer(r"[0-9]+", header[shape:header.index(")")]))]


def _cine_fields(data: bytes) -> list[Field]:
    """The CINEFILEHEADER's and BITMAPINFOHEADER's integers, and SETUP's FrameRate, as (offset, size) fields."""
    cine_header = [("Headersize", 2, 2, "unused"), ("Compression", 4, 2, "used"), ("Version", 6, 2, "used"),
                   ("FirstMovieImage", 8, 4, "unused"), ("TotalImageCount", 12, 4, "unused"),
                   ("FirstImageNo", 16, 4, "used"), ("ImageCount", 20, 4, "used"), ("OffImageHeader", 24, 4, "used"),
                   ("OffSetup", 28, 4, "used"), ("OffImageOffsets", 32, 4, "used"), ("TriggerTime", 36, 8, "unused")]
    bitmap = struct.unpack_from("<I", data, 24)[0]
    bitmap_header = [("biSize", 0, 4, "used"), ("biWidth", 4, 4, "used"), ("biHeight", 8, 4, "used"),
                     ("biPlanes", 12, 2, "used"), ("biBitCount", 14, 2, "used"), ("biCompression", 16, 4, "used"),
                     ("biSizeImage", 20, 4, "used"), ("biXPelsPerMeter", 24, 4, "unused"),
                     ("biYPelsPerMeter", 28, 4, "unused"), ("biClrUsed", 32, 4, "used"),
                     ("biClrImportant", 36, 4, "used")]
    fields = [Field(name, off, off + size, use) for name, off, size, use in cine_header]
    fields += [Field(name, bitmap + off, bitmap + off + size, use) for name, off, size, use in bitmap_header]
    setup, offsets = struct.unpack_from("<II", data, 28)
    rate = struct.pack("<I", 100)   # pyidi's sample: 100 fps; FrameRate is the 4-byte one of the SETUP that says so
    at = data.find(rate, setup, offsets)
    while at >= 0 and at % 2:
        at = data.find(rate, at + 1, offsets)
    if at >= 0:
        fields.append(Field("FrameRate", at, at + 4, "rate"))
    return fields


# ------------------------------------------------------------------ the bases: real files and the rigs that import them

def _bases(shared: Path, rng: random.Random) -> list[Base]:
    def read(rel: str) -> bytes:
        return (shared / rel).read_bytes()

    tutorial, pyidi, pymraw = "ladisk-imaging-tutorial", "pyidi-samples", "pymraw-samples"
    bases = []
    lvm = read(f"{tutorial}/acceleration.lvm")
    bases.append(Base("lvm", {"a.lvm": lvm}, 'name = "f"\n' + LADISK_CHANNELS + '[[takes]]\nsignals = "a.lvm"\n'
                      "pretrigger_samples = 30\n", "a.lvm", _lvm_fields(lvm.decode()), 1000))
    for name, rel in (("cih_ladisk", f"{tutorial}/focus.cih"), ("cih_pyidi", f"{pyidi}/data_showcase.cih")):
        cih = read(rel)
        bases.append(Base(name, {"cam.cih": cih, "cam.mraw": read(rel.replace(".cih", ".mraw"))},
                          'name = "f"\n[[takes]]\nvideo = "cam.cih"\n', "cam.cih",
                          _cih_fields(cih.decode("latin-1")), len(cih)))
    for name, rel in (("cihx_beam", f"{pymraw}/beam.cihx"), ("cihx_ball", f"{pymraw}/ball_12bit.cihx")):
        cihx = read(rel)
        bases.append(Base(name, {"cam.cihx": cihx, "cam.mraw": read(rel.replace(".cihx", ".mraw"))},
                          'name = "f"\n[[takes]]\nvideo = "cam.cihx"\n', "cam.cihx",
                          _cihx_fields(cihx.decode("latin-1")), len(cihx)))
    cine = read(f"{pyidi}/data_small_cine.cine")
    bases.append(Base("cine", {"cam.cine": cine}, 'name = "f"\n[[takes]]\nvideo = "cam.cine"\n', "cam.cine",
                      _cine_fields(cine), 2048, binary_fields=True))
    # A uint8 .npy of the real showcase frames; pyidi's and pyFRF's own arrays (float, refused as video) as they are.
    showcase = np.fromfile(shared / pyidi / "data_showcase.mraw", dtype=np.uint8).reshape(75, 40, 640)
    arrays = {"npy_showcase": showcase, "npy_pyidi": np.load(shared / pyidi / "data_synthetic_generated.npy"),
              "npy_pyfrf": np.load(shared / "pyfrf-hits" / "measurements_1.npy")}
    for name, array in arrays.items():
        blob = _npy_bytes(array)
        bases.append(Base(name, {"x.npy": blob}, 'name = "f"\n[[takes]]\nvideo = "x.npy"\nfps = 15000\n', "x.npy",
                          _npy_fields(blob), 128))
    for name, rel, column in (("uff_ascii", "time-history-not-all-columns-filled.uff", "1x : m/s²"),
                              ("uff_binary", "binary8byte.uff", "rsp_node1_dir0"),
                              ("uff_58b", "Sample_UFF58b_bin.uff", "Mic 01.0Scalar")):
        uff = read(f"pyuff-samples/{rel}")
        kind = "pressure" if "Mic" in column else "acceleration"
        channel = f'[[channels]]\nname = "ch"\nkind = "{kind}"\ncolumn = "{column}"\n'
        fields = _uff_fields(uff.decode("latin-1")) if rel.endswith("filled.uff") else []
        bases.append(Base(name, {"a.uff": uff}, 'name = "f"\n' + channel + '[[takes]]\nsignals = "a.uff"\n', "a.uff",
                          fields, 1200 if "58b" in rel else len(uff) // 2))
    # pyFRF's hits as the CSV a DAQ exports: time, force, acceleration.
    hits = np.load(shared / "pyfrf-hits" / "measurements_1.npy")[:, :6000]
    csv = ("time [s],force [N],acc [m/s^2]\n" + "".join(f"{t:.17g},{f:.17g},{a:.17g}\n" for t, f, a in hits.T)).encode()
    bases.append(Base("csv", {"daq.csv": csv}, 'name = "f"\n' + CHANNELS.format(force="force", acc="acc")
                      + '[[takes]]\nsignals = "daq.csv"\n', "daq.csv", _csv_fields(csv.decode(), rng), 40,
                      counted=False))
    focus = f"{tutorial}/focus"
    bases.append(Base("mraw", {"cam.cih": read(f"{focus}.cih"), "cam.mraw": read(f"{focus}.mraw")},
                      'name = "f"\n[[takes]]\nvideo = "cam.cih"\n', "cam.mraw", [], 25600))
    # A rig of every kind of field, over the showcase .npy and the CSV.
    rig = ('name = "f"\nnotes = "fuzz"\n[camera]\nexposure_s = 6.5e-5\nbit_depth = 8\n'
           '[camera.intrinsics]\nfx_px = 1200.0\nfy_px = 1200.0\ncx_px = 320.0\ncy_px = 20.0\n'
           '[tags]\nsize_m = 0.03\n[[tags.tags]]\nid = 0\ncorners_m = [[0, 0, 0], [0.03, 0, 0], [0.03, 0.03, 0], '
           '[0, 0.03, 0]]\n'
           + CHANNELS.format(force="force", acc="acc").replace('column = "acc"\n', 'column = "acc"\n'
                                                               'position_m = [0.1, 0.0, 0.02]\ndirection = [0, 0, 1]\n'
                                                               'sensitivity_v_per_unit = 0.01\n')
           + '[[takes]]\nname = "hit"\nview = 2\nvideo = "x.npy"\nsignals = "daq.csv"\nfps = 15000\n'
             'pretrigger_samples = 30\ncamera_trigger_time_s = 0.0006\ntrigger_frame = 3\n')
    rates = {"fps", "sample_rate_hz"}
    rig_fields = [Field(m[1], m.start(2), m.end(2), "rate" if m[1] in rates else "used")
                  for m in re.finditer(r"^(\w+) = (-?[0-9.e-]+)$", rig, re.M)]
    rig_fields += [Field(f"{m[1]}[0]", m.start(2), m.end(2), "used")
                   for m in re.finditer(r"^(\w+) = \[\[?(-?[0-9.]+)", rig, re.M)]
    bases.append(Base("rig", {"x.npy": _npy_bytes(showcase), "daq.csv": csv}, rig, "rig.toml", rig_fields, 0))
    return bases


def _npy_bytes(array: np.ndarray) -> bytes:
    import io

    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


# ------------------------------------------------------------------ the mutations

def _replace(data: bytes, field: Field, value: str, binary: bool) -> bytes:
    if binary:
        size = field.end - field.start
        number = int(value) & ((1 << (8 * size)) - 1)
        return data[:field.start] + number.to_bytes(size, "little") + data[field.end:]
    width = field.end - field.start
    if data[field.start:field.end].startswith(b" "):   # a fixed-width field (UFF): the value right-aligned in it
        return data[:field.start] + value.rjust(width).encode() + data[field.end:]
    return data[:field.start] + value.encode() + data[field.end:]


def _field_expectation(field: Field, value: str) -> str:
    if field.use == "unused":
        return "same"
    if field.use == "pyuff's":
        return "refused_or_same"
    if value in NOT_A_NUMBER and field.use != "data":
        return "refused"
    if field.use == "data":   # a sample: not a number, or one float32 cannot hold, is refused; others are data
        return "refused" if value in NOT_A_NUMBER or value in ("1e308", "-1e308") else "any"
    if value in EXTREME and field.use == "rate":
        return "refused"
    return "refused_or_same"


def _cases(bases: list[Base], rng: random.Random, per_base: int) -> list[Case]:
    cases = []
    for base in bases:
        target = base.rig.encode() if base.target == "rig.toml" else base.files[base.target]
        kinds = ["field"] * 3 * bool(base.fields) + ["truncate", "bitflip"] * (base.target != "rig.toml")
        for _ in range(per_base):
            kind = rng.choice(kinds)
            if kind == "truncate":
                cut = rng.randrange(0, len(target))
                if rng.random() < 0.5 and b"\n" in target[:cut]:   # at a line boundary, as a copy cut short
                    cut = target.rindex(b"\n", 0, cut) + 1
                data, detail = target[:cut], f"{cut} of {len(target)} bytes"
                expect = "refused_or_same" if base.counted else "any"
            elif kind == "bitflip":
                flipped = bytearray(target)
                bits = [rng.randrange(0, min(base.header_bytes, len(target)) * 8) for _ in range(rng.randint(1, 3))]
                for bit in bits:
                    flipped[bit // 8] ^= 1 << (bit % 8)
                data, detail, expect = bytes(flipped), f"bits {bits}", "any"
            else:
                field = rng.choice(base.fields)
                if base.binary_fields:
                    plausible = rng.random() < 0.4
                    value = str(rng.choice([0, 1, 7] if plausible else [2**31 - 1, 2**32 - 1, 2**31,
                                                                         rng.getrandbits(32)]))
                    # A plausible count (7 of a cine's 235 images) reads what it says: no second source to check.
                    expect = "same" if field.use == "unused" else "any" if plausible else "refused_or_same"
                else:
                    value = rng.choice(NOT_A_NUMBER + EXTREME + PLAIN)
                    expect = _field_expectation(field, value)
                data, detail = _replace(target, field, value, base.binary_fields), f"{field.label} = {value!r}"
            if base.target == "rig.toml":
                cases.append(Case(base.name, kind, detail, base.files, data.decode(), expect))
            else:
                cases.append(Case(base.name, kind, detail, {**base.files, base.target: data}, base.rig, expect))
    return cases


def _rig_cases(base: Base) -> list[Case]:
    """Names and paths that would leave the capture or break a file name; a NUL or 300 characters."""
    cases = []
    take_names = ["../../x", "/tmp/odsplat-fuzz-x", "a/b", "..", ".", "a\\u0000b", "n" * 300, "a\\\\b", " x", "-x"]
    for name in take_names:
        cases.append(Case("rig", "name", f"take {name[:20]!r}", base.files,
                          base.rig.replace('name = "hit"', f'name = "{name}"'), "refused"))
    cases.append(Case("rig", "name", "take 'hit.2-b_c'", base.files,
                      base.rig.replace('name = "hit"', 'name = "hit.2-b_c"'), "same"))
    for name in ["a/b", "a\\u0000b", "c" * 300, ".", "..", "x y", ""]:
        cases.append(Case("rig", "name", f"channel {name[:20]!r}", base.files,
                          base.rig.replace('name = "acc"', f'name = "{name}"'), "refused_or_same"))
    cases.append(Case("rig", "name", "capture with NUL", base.files,
                      base.rig.replace('name = "f"', 'name = "a\\u0000"'), "refused"))
    for field in ("video", "signals"):
        current = "x.npy" if field == "video" else "daq.csv"
        for path in ["../../../../../../etc/passwd", "/etc/passwd", "../outside", "", " ", "/", "..", "."]:
            cases.append(Case("rig", "path", f"{field} {path!r}", base.files,
                              base.rig.replace(f'{field} = "{current}"', f'{field} = "{path}"'), "refused"))
        cases.append(Case("rig", "path", f"{field} through ../data", base.files,
                          base.rig.replace(f'{field} = "{current}"', f'{field} = "../data/{current}"'), "same"))
    for pattern in ["../../../../../../etc/passwd", "/etc/*", "../*", "*/../../*", "nothing*"]:
        cases.append(Case("rig", "path", f"static {pattern!r}", base.files, f'static = ["{pattern}"]\n' + base.rig,
                          "refused"))
    return cases


# ------------------------------------------------------------------ running one input

class _Hung(BaseException):
    """Raised by the alarm: a BaseException, so no `except Exception` in the code under test can swallow it."""


def _alarm(signum, frame):
    raise _Hung()


def _listing(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _contents(out: Path) -> list[np.ndarray]:
    """Every take's frames and samples, in order."""
    cap = Capture.open(out)
    arrays = []
    for take in cap.manifest.takes:
        with cap.open_take(take.name) as reader:
            if reader.has_frames:
                arrays.append(reader.read_frames())
            arrays += [np.asarray(reader.channel(c.name)) for c in cap.manifest.channels if reader.n_samples]
    return arrays


def _same(a: list[np.ndarray], b: list[np.ndarray]) -> bool:
    return len(a) == len(b) and all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(a, b))


def _run(tmp: Path, case: Case, pristine: dict[str, tuple[Path, bytes]]) -> str:
    """Import one input, its files in tmp/caseN/data and OUT tmp/caseN/out; returns refused, imported (leaving OUT),
    or a failure: traceback, hang, partial, stray (a file appeared or went anywhere under tmp but OUT)."""
    case_dir = tmp / "case"
    data = case_dir / "data"
    data.mkdir(parents=True)
    for name, blob in case.files.items():
        if name in pristine and blob is pristine[name][1]:
            os.link(pristine[name][0], data / name)   # the unchanged files: no copy of megabytes per input
        else:
            (data / name).write_bytes(blob)
    rig = data / "rig.toml"
    rig.write_text(case.rig)
    out = case_dir / "out"
    before = _listing(tmp)
    previous = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, TIMEOUT_S)
    faulthandler.dump_traceback_later(3 * TIMEOUT_S, exit=True)   # a hang the alarm cannot break: fail loudly
    try:
        import_capture(rig, out)
        outcome = "imported"
    except (InputError, OdsplatError) as exc:
        outcome = "refused" if "\n" not in str(exc) else f"traceback: more than one line: {exc}"
    except _Hung:
        outcome = f"hang: no result in {TIMEOUT_S:g} s"
    except Exception as exc:  # noqa: BLE001 - what the test looks for
        outcome = f"traceback: {type(exc).__name__}: {exc}"
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        faulthandler.cancel_dump_traceback_later()
    after = _listing(tmp)
    made = {p for p in after - before if not (outcome == "imported" and Path(p).is_relative_to("case/out"))}
    if made or before - after:
        return f"stray: {sorted(made)[:4]} appeared, {sorted(before - after)[:4]} went"
    if outcome == "refused" and out.exists():
        return "partial: refused, but OUT exists"
    return outcome


_MEETS = {"refused": {"refused"}, "same": {"imported_same"}, "refused_or_same": {"refused", "imported_same"},
          "any": {"refused", "imported_same", "imported_differs"}}


def test_import_fuzz(shared_data, tmp_path):
    started = time.perf_counter()
    rng = random.Random(SEED)
    bases = _bases(shared_data, rng)
    cases = _cases(bases, rng, per_base=PER_BASE) + _rig_cases(bases[-1])
    work = tmp_path / "work"
    work.mkdir()
    for base in bases:   # the uncorrupted inputs import (pyidi's and pyFRF's float arrays are refused as video)
        store = tmp_path / "pristine" / base.name
        store.mkdir(parents=True)
        for name, blob in base.files.items():
            (store / name).write_bytes(blob)
        base.pristine = {name: (store / name, blob) for name, blob in base.files.items()}
        outcome = _run(work, Case(base.name, "baseline", "", base.files, base.rig, ""), base.pristine)
        assert outcome == ("refused" if base.name in ("npy_pyidi", "npy_pyfrf") else "imported"), (base.name, outcome)
        base.baseline = _contents(work / "case" / "out") if outcome == "imported" else None
        shutil.rmtree(work / "case")
    by_name = {b.name: b for b in bases}
    results: Counter[tuple[str, str]] = Counter()
    failures = []
    for case in cases:
        base = by_name[case.base]
        outcome = _run(work, case, base.pristine)
        if outcome == "imported":
            same = base.baseline is not None and _same(_contents(work / "case" / "out"), base.baseline)
            outcome = "imported_same" if same else "imported_differs"
        results[case.kind, outcome.split(":")[0]] += 1
        if outcome not in _MEETS[case.expect]:
            failures.append(f"{case.base} {case.kind} {case.detail}: expected {case.expect}, got {outcome}")
        shutil.rmtree(work / "case")
    elapsed = time.perf_counter() - started
    print(f"\n{len(cases)} inputs from {len(bases)} bases in {elapsed:.1f} s (seed {SEED}):")
    for (kind, outcome), n in sorted(results.items()):
        print(f"  {kind:9s} {outcome:17s} {n}")
    assert not list(Path("/tmp").glob("odsplat-fuzz-x*")), "a take named by an absolute path was written there"
    assert not failures, f"{len(failures)} of {len(cases)} inputs:\n" + "\n".join(failures)
