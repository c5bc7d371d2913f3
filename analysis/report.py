"""A self-contained HTML report of an analysis (derived/analysis/analysis.json and its plots): one file, CSS and
images inline, that can be mailed.

analysis.json is data a user may edit by hand, so nothing in it reaches the page as HTML: this module turns it into
plain text (numbers formatted, rows listed, flags for the CSS classes), and the Jinja2 templates in `templates/`
lay that out with every value escaped. Images are inlined only from files the analysis itself wrote in its own
folder (`_own_file`), read here and encoded here; a file name that leads anywhere else is shown, escaped, with why
it was left out."""
from __future__ import annotations

import base64
import html
import io
import json
import logging
import math
import os
import stat
from pathlib import Path, PurePosixPath, PureWindowsPath

import jinja2
import numpy as np
from markupsafe import Markup

from odsplat.reconstruction import PoseResult
from odsplat.spine.contract import check
from odsplat.spine.errors import InputError
from odsplat.spine.guard import check_inside
from odsplat.spine.manifest import load_json
from odsplat.spine.store import Capture, atomic_write_text
from odsplat.sync import load_sync

from .analyze import KIND, SCHEMA

log = logging.getLogger(__name__)


def _escaped(value) -> Markup:
    """Every value a template prints, escaped as `html.escape` escapes it (&, <, >, " and ', the last as &#x27;,
    as the report always wrote them); autoescape then leaves the result alone. Markup passes unchanged: only the
    templates make it (a macro's output, a `set` block), from their own text and values escaped here."""
    if isinstance(value, Markup):
        return value
    return Markup(html.escape(str(value)))


_TEMPLATES = jinja2.Environment(loader=jinja2.FileSystemLoader(Path(__file__).with_name("templates")),
                                autoescape=True, undefined=jinja2.StrictUndefined, finalize=_escaped,
                                trim_blocks=True, lstrip_blocks=True, keep_trailing_newline=True)


# ---------------------------------------------------------------------------------------------- reading

def _field(d: dict, key: str, kind, where: str, default=...):
    """d[key] checked to be of `kind`; a missing or mistyped field raises InputError naming it."""
    if key not in d:
        if default is not ...:
            return default
        raise InputError(f"{where}: {key}", "missing")
    v = d[key]
    if not isinstance(v, kind) or isinstance(v, bool) and kind is not bool:
        raise InputError(f"{where}: {key}", f"expected {_kind_name(kind)}; got {type(v).__name__}")
    return v


def _kind_name(kind) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join({int: "a number", float: "a number", list: "a list", dict: "an object",
                        str: "a string", type(None): "null"}.get(k, k.__name__) for k in kinds)


_NUM = (int, float)


def read_analysis(capture: Capture) -> dict:
    """The capture's analysis.json, checked: its header (kind, schema, capture) and the fields the report uses."""
    path = capture.paths.analysis_json
    doc = load_json(path, missing="no analysis (run `odsplat analyze` first)")
    check(doc, path, kind=KIND, schema_version=SCHEMA, capture_id=capture.id)
    for k, m in enumerate(_field(doc, "modes", list, str(path))):
        w = f"{path}: modes[{k}]"
        if not isinstance(m, dict):
            raise InputError(w, "expected an object with freq_hz and damping")
        _field(m, "freq_hz", _NUM, w), _field(m, "damping", _NUM, w)
    _field(doc, "files", dict, str(path), {})
    _field(doc, "rejected_hits", list, str(path), [])
    for key in ("video", "correlation"):
        _field(doc, key, (dict, type(None)), str(path), None)
    _field(doc, "ods", list, str(path), [])
    return doc


# ---------------------------------------------------------------------------------------------- plain values
# read_analysis checks only what every section needs; the rest of the document is taken as it comes, so each
# value is read through one of these and a field of the wrong kind shows as a dash or an empty table, never
# as an error half-way through the page.

DASH = "\u2013"    # where a number is missing or is no finite number


def _obj(x) -> dict:
    return x if isinstance(x, dict) else {}


def _list(x) -> list:
    return x if isinstance(x, list) else []


def _dicts(x) -> list[dict]:
    return [d for d in _list(x) if isinstance(d, dict)]


def _float(x) -> float | None:
    """x as a finite float, or None (missing, text, a flag, infinite, NaN)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return None
    try:
        v = float(x)
    except OverflowError:
        return None
    return v if math.isfinite(v) else None


def _index(x, n: int) -> int | None:
    """x as an index into a list of n, or None where it is no whole number in 0..n-1."""
    v = _float(x)
    return int(v) if v is not None and v == int(v) and 0 <= v < n else None


def _num(x, fmt: str = ".3g", scale: float = 1.0) -> str:
    """x times scale formatted with fmt; a dash where x is no finite number."""
    try:
        v = float(x) * scale
    except (TypeError, ValueError, OverflowError):
        return DASH
    if not np.isfinite(v):
        return DASH
    text = format(v, fmt)
    return format(0.0, fmt) if float(text) == 0 else text      # no "-0.0"


def _count(x) -> str:
    """A count (points, views, pixels, timesteps) as a whole number; a dash where x is no finite number."""
    v = _float(x)
    return DASH if v is None else str(int(v))


def _mode_name(modes: list[dict], k) -> str:
    """Mode k by number and frequency ("2 (31.00 Hz)"), or k as it stands where it names no mode."""
    i = _index(k, len(modes))
    return f"{i + 1} ({_num(modes[i]['freq_hz'], '.2f')} Hz)" if i is not None else str(k)


def _fitted_mode(fitted: list, b):
    """The accelerometer mode the video's b-th fitted mode is (modes_fitted[b]); b itself where b indexes none."""
    i = _index(b, len(fitted))
    return fitted[i] if i is not None else b


# ---------------------------------------------------------------------------------------------- sections

def _reasons(r) -> list[str]:
    return [r] if isinstance(r, str) else [str(x) for x in r] if isinstance(r, list) else []


def _summary(doc: dict, setup: dict) -> dict:
    """The page's top: the setup, the modes with their MAC, and the verdict line."""
    modes = doc["modes"]
    fitted = _list(_obj(doc.get("video")).get("modes_fitted"))
    c = _obj(doc.get("correlation"))
    by_mode = {}
    for p in _dicts(c.get("pairs")):
        b = _index(p.get("b"), len(fitted))
        k = _index(fitted[b], len(modes)) if b is not None else None
        if k is not None:
            by_mode[k] = p
    rows = []
    for k, m in enumerate(modes):
        p = by_mode.get(k)
        rows.append({"mode": str(k + 1), "freq": _num(m["freq_hz"], ".2f"), "damping": _num(m["damping"], ".2f", 100),
                     "mac": DASH if p is None else _num(p.get("mac"), ".3f"),
                     "below": p is not None and bool(p.get("below_noise_floor")),
                     "scale": DASH if p is None else _num(p.get("scale_factor_abs"), ".2f")})
    verdict = _obj(c.get("verdict"))
    notes = _list(doc.get("notes"))
    band = _list(doc.get("band_hz")) or [None]
    setup_rows = [[str(k), str(v)] for k, v in setup.items()]
    setup_rows += [["hits averaged", f"{doc.get('n_averages', '?')} of {len(_list(doc.get('takes')))}"],
                   ["sensors", ", ".join(str(s) for s in _list(doc.get("sensors")))],
                   ["fit band", f"{_num(band[0], '.0f')} to {_num(band[-1], '.0f')} Hz"]]
    return {"verdict": str(verdict["line"]) if verdict.get("line") else None,
            "css": "ok" if verdict.get("status") == "met" else ("bad" if notes or verdict.get("line") else ""),
            "video": bool(doc.get("video")), "n_modes": len(modes), "n_notes": len(notes),
            "setup": setup_rows, "modes": rows}


def _notes(doc: dict) -> list[str]:
    """What the numbers cannot show, at the top: peaks with no mode, a band that cuts a peak, missing geometry."""
    return [str(n) for n in _list(doc.get("notes"))]


def _hits(doc: dict) -> dict:
    takes = [str(t) for t in _list(doc.get("takes"))]
    rejected = {str(r.get("take")): _reasons(r.get("reasons")) for r in _dicts(doc["rejected_hits"])}
    rows = [{"take": t, "used": t not in rejected, "reasons": "; ".join(rejected.get(t, []))} for t in takes]
    rows += [{"take": t, "used": False, "reasons": "; ".join(r)} for t, r in rejected.items() if t not in takes]
    return {"n_used": len([t for t in takes if t not in rejected]), "n_takes": len(takes),
            "averages": str(doc["n_averages"]) if "n_averages" in doc else None,
            "tau_ms": _num(doc["exp_tau_s"], ".3g", 1e3) if doc.get("exp_tau_s") else None, "rows": rows}


def _modes(doc: dict) -> dict:
    band = doc.get("band_hz")
    return {"band": ([_num(band[0], ".0f"), _num(band[1], ".0f")] if isinstance(band, list) and len(band) == 2
                     else None),
            "rows": [[str(k + 1), _num(m["freq_hz"], ".2f"), _num(m["damping"], ".2f", 100)]
                     for k, m in enumerate(doc["modes"])]}


def _video(doc: dict) -> dict | None:
    """The video side: what was fitted to the reconstruction's motion, its noise, its own poles and the 2D
    cross-check; None where the analysis has no video side."""
    v = doc.get("video")
    if not v:
        return None
    modes = doc["modes"]
    out = {"fitted": ", ".join(_mode_name(modes, k) for k in _list(v.get("modes_fitted"))) or "none",
           "surface": None, "window": None, "condition": None, "real": None, "r2": [], "poles": None,
           "image_poles": None, "noise": None, "crosscheck": []}
    if "n_surface_points" in v:
        background = None
        if v.get("n_background_points"):
            background = {"rule": str(v.get("structure_rule", "")), "n": _count(v["n_background_points"]),
                          "rms": _num(v.get("background_rms_um"), ".3g"), "amplitude": None}
            if v.get("background_amplitude_ratio") is not None:
                background["amplitude"] = {
                    "um": _num(v.get("background_amplitude_um"), ".3g"),
                    "n_reference": _count(v.get("n_background_reference_points", 0)),
                    "ratio": _num(v["background_amplitude_ratio"], ".1f", 100),
                    "ratio_all": _num(v.get("background_amplitude_ratio_all"), ".1f", 100)}
        out["surface"] = {"n": _count(v["n_surface_points"]), "background": background}
    window = v.get("window_s")
    if isinstance(window, list) and len(window) == 2:
        out["window"] = [_num(window[0], ".1f", 1e3), _num(window[1], ".1f", 1e3)]
    if "condition" in v:
        out["condition"] = _num(v["condition"], ".3g")
    real = _dicts(v.get("real_modes"))
    if real:
        ratios = [r for r in (_float(m.get("quadrature_over_noise")) for m in real if m.get("real")) if r is not None]
        out["real"] = {"n_real": sum(bool(m.get("real")) for m in real), "n": len(real),
                       "ratios": [_num(min(ratios), ".2f"), _num(max(ratios), ".2f")] if ratios else None}
    sensors = [str(s) for s in _list(doc.get("sensors"))]
    out["r2"] = _sensor_rows(sensors, _list(v.get("sensor_r2")))
    pairs = _dicts(_obj(doc.get("correlation")).get("pairs"))
    out["poles"] = _poles(modes, v.get("freq_hz"), v.get("damping"), pairs)
    im = doc.get("image_poles")
    if isinstance(im, dict):
        window = _list(im.get("window_s")) or [None]
        out["image_poles"] = {"n_views": _count(im.get("n_views", 0)), "n_pixels": _count(im.get("n_pixels", 0)),
                              "window": [_num(window[0], ".1f", 1e3), _num(window[-1], ".1f", 1e3)],
                              **_poles(modes, im.get("freq_hz"), im.get("damping"), pairs)}
    out["noise"] = _noise(v)
    checks = _dicts(v.get("crosscheck"))
    if checks:
        out["crosscheck_verdict"] = _verdict(v.get("crosscheck_verdict"))
        out["crosscheck"] = [[str(c.get("take", "")), _count(c.get("n_points")), _num(c.get("gain"), ".2f"),
                              _num(c.get("correlation"), ".2f"), _num(c.get("motion_rms_px"), ".3f"),
                              _num(c.get("noise_px"), ".4f"), _num(c.get("force_ratio"), ".2f")] for c in checks]
    return out


def _verdict(v) -> dict | None:
    """A verdict's line and status, with the CSS class of its colour."""
    if not isinstance(v, dict) or "line" not in v:
        return None
    status = str(v.get("status", ""))
    return {"css": {"met": "ok", "not met": "bad"}.get(status, "meta"), "status": status, "line": str(v["line"])}


def _noise(v: dict) -> dict | None:
    """The video's noise floor: where it was measured, and in metres."""
    nf = v.get("noise_floor")
    if not isinstance(nf, dict):
        return None
    k = nf.get("floor_sigmas")
    kf = _float(k)
    at_floor = nf.get("floor_mac", kf * kf / (kf * kf + 1) if kf is not None else None)   # older files
    return {"sigma": _num(nf.get("sigma_um"), ".3g"),
            "static": ({"n": _count(nf["n_static_points"]), "sigma": _num(nf.get("static_sigma_um"), ".3g")}
                       if nf.get("n_static_points") else None),
            "pre_impact": ({"n": _count(nf.get("n_pre_impact", 0)), "sigma": _num(nf.get("pre_impact_sigma_um"), ".3g")}
                           if nf.get("pre_impact_sigma_um") is not None else None),
            "sigmas": _num(k, ".3g"), "mac": _num(at_floor, ".2f")}


def _products(modes: list[dict], pairs: list[dict]) -> list[tuple[float, str]]:
    """The second-order products of the video's two strongest modes (by their video amplitude): twice each, their
    sum and their difference, with names. A camera's intensity is not quite linear in the motion, so the strongest
    motion leaves a little energy there, and a pole finder can find it."""
    amps = {}
    for p in pairs:
        k, a = _index(p.get("a"), len(modes)), _float(p.get("video_amplitude_um"))
        if k is not None and a is not None:
            amps[k] = a
    top = sorted(amps, key=lambda k: -amps[k])[:2]
    f = {k: float(modes[k]["freq_hz"]) for k in top}
    out = [(2 * f[k], f"2 x mode {k + 1}") for k in top]
    if len(top) == 2:
        a, b = top
        out += [(f[a] + f[b], f"mode {a + 1} + mode {b + 1}"), (abs(f[a] - f[b]), f"mode {a + 1} - mode {b + 1}")]
    return out


def _poles(modes: list[dict], fv, zv, pairs: list[dict]) -> dict:
    """The camera's own poles against the nearest accelerometer mode; one more than 1 % from every mode is said to
    be no mode of theirs, and named where it lies near a product of the strongest motion (`_products`)."""
    fv, zv = _list(fv), _list(zv)
    fa = np.array([_float(m["freq_hz"]) or np.nan for m in modes], float)
    products = _products(modes, pairs)
    rows = []
    for i, x in enumerate(fv):
        f = _float(x)
        near = int(np.nanargmin(np.abs(fa - f))) if f is not None and np.isfinite(fa).any() else None
        diff = (f - fa[near]) / fa[near] if near is not None else None
        row = {"n": str(i + 1), "freq": _num(f, ".2f"), "damping": _num(zv[i] if i < len(zv) else None, ".2f", 100),
               "mode": _mode_name(modes, near) if near is not None else DASH, "diff": _num(diff, "+.2f", 100),
               "off": False, "near": None}
        if f is not None and (diff is None or abs(diff) > 0.01):
            row["off"] = True
            close = [(abs(f - fp) / fp, fp, name) for fp, name in products if fp > 0 and abs(f - fp) < 0.05 * fp]
            if close:
                _, fp, name = min(close)
                row["near"] = {"name": name, "freq": f"{fp:.1f}"}
        rows.append(row)
    return {"rows": rows}


def _poles_table(modes: list[dict], fv, zv, title: str, empty: str, pairs: list[dict] | None = None) -> str:
    """One table of poles (`_poles`) as the page lays it out, under `title` (the line `empty` where there are none)."""
    macros = _TEMPLATES.get_template("macros.html").module
    return str(macros.poles_table(_poles(modes, fv, zv, pairs or []), title, empty))


def _sensor_rows(sensors: list[str], values: list) -> list[list[str]]:
    """One value per sensor (named, or numbered where the document has fewer names)."""
    return [[sensors[j] if j < len(sensors) else f"sensor {j + 1}", _num(x, ".3f")] for j, x in enumerate(values)]


def _correlation(doc: dict) -> dict:
    c = doc.get("correlation")
    modes = doc["modes"]
    fitted = _list(_obj(doc.get("video")).get("modes_fitted"))
    out = {"pairs": None, "verdict": None, "comac": [], "ods": []}
    if c:
        rows = []
        for p in _dicts(c.get("pairs")):
            rows.append({"a": _mode_name(modes, _fitted_mode(fitted, p.get("a"))),
                         "b": _mode_name(modes, _fitted_mode(fitted, p.get("b"))),
                         "mac": _num(p.get("mac"), ".3f"), "below": p.get("below_noise_floor") is True,
                         "expected": _num(p.get("expected_mac"), ".3f"),
                         "amplitude": _num(p.get("video_amplitude_um"), ".3g"),
                         "floor": _num(p.get("noise_floor_um"), ".3g"),
                         "scale": _num(p.get("scale_factor_abs"), ".3g"),
                         "phase": _num(p.get("scale_factor_phase_deg"), "+.1f"),
                         "freq_a": _num(p.get("freq_a_hz"), ".2f"), "freq_b": _num(p.get("freq_b_hz"), ".2f"),
                         "diff": _num(p.get("freq_diff_rel"), "+.2f", 100)})
        out["pairs"] = rows
        out["verdict"] = _verdict(c.get("verdict"))
        out["comac"] = _sensor_rows([str(s) for s in _list(doc.get("sensors"))], _list(c.get("comac")))
    out["ods"] = [[str(i + 1), _num(o.get("freq_hz"), ".2f"), _num(o.get("mac"), ".3f")]
                  for i, o in enumerate(doc.get("ods", [])) if isinstance(o, dict)]
    return out


def _settings(doc: dict) -> str | None:
    s = doc.get("settings")
    return json.dumps(s, indent=1) if s else None


# ---------------------------------------------------------------------------------------------- inlined files

_ANALYSIS_FOLDER = "derived/analysis"
_SIGNATURES = {".png": (b"\x89PNG\r\n\x1a\n",), ".gif": (b"GIF87a", b"GIF89a")}
_MEDIA = {".png": "image/png", ".gif": "image/gif"}


def _own_file(folder: Path, rel, where: str = _ANALYSIS_FOLDER, writer: str = "the analysis") -> Path | str:
    """The file `rel` names in `folder`, or why it is not one of the folder's own (one line). Its own: a relative
    name of plain parts ("plots/frf.png": no `..`, `.` or empty part, no absolute path or drive, no backslash),
    no symbolic link on the way from `folder` down (the file included), a regular file, and inside `folder` once
    resolved. `where` names the folder in the line, `writer` what writes its files."""
    outside = f"not a file {writer} wrote (outside {where})"
    if not isinstance(rel, str) or not rel:
        return outside
    parts = rel.split("/")
    if (PurePosixPath(rel).is_absolute() or PureWindowsPath(rel).anchor or "\\" in rel or "\0" in rel
            or any(p in ("", ".", "..") for p in parts)):
        return outside
    path = folder.joinpath(*parts)
    try:   # the parts are plain, so the one thing it can refuse is a link on the way
        check_inside(folder, path)
    except InputError:
        return f"not a file {writer} wrote (a symbolic link)"
    if not path.exists():
        return "not found"
    if not path.is_file():
        return "not a regular file"
    if not path.resolve().is_relative_to(folder.resolve()):
        return outside
    return path


def _read_own(path: Path) -> bytes:
    """A file `_own_file` accepted, opened without following a link (a link put in its place after the check makes
    the open fail) and read only if it is still a regular file."""
    flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
    with os.fdopen(os.open(path, flags), "rb") as fh:
        if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
            raise OSError(f"{path}: not a regular file")
        return fh.read()


def _data_uri(media: str, data: bytes) -> str:
    """A data: URI of bytes read here: base64 holds no character HTML would need escaped."""
    return f"data:{media};base64,{base64.b64encode(data).decode('ascii')}"


def _inline(doc: dict, folder: Path, suffix: str) -> list[dict]:
    """Each output file of the analysis ending in `suffix`, as {"key", "file", "src"} with its data: URI, or with
    "problem" (one line naming the file) where it is missing ("missing" set) or is no file of the analysis's own
    in `folder`, or no image of its kind."""
    out = []
    for key, rel in doc["files"].items():
        if not (isinstance(rel, str) and rel.lower().endswith(suffix)):
            continue
        item = {"key": str(key), "file": rel, "src": None, "problem": None, "missing": False}
        out.append(item)
        path = _own_file(folder, rel)
        if path == "not found":
            item.update(problem=f"{rel} not found.", missing=True)
        elif isinstance(path, str):
            item["problem"] = f"{rel}: {path}"
        else:
            try:
                data = _read_own(path)
            except OSError as e:
                item["problem"] = f"{rel}: could not be read ({e.strerror or e})"
            else:
                if data.startswith(_SIGNATURES[suffix]):
                    item["src"] = _data_uri(_MEDIA[suffix], data)
                else:
                    item["problem"] = f"{rel}: not a {suffix[1:].upper()} image"
        if item["problem"]:
            log.warning("report: %s; left out", item["problem"])
    return out


def _animations(doc: dict, folder: Path) -> list[dict]:
    """The modes in motion: each animation inline (a GIF in the page itself), captioned with its mode's number."""
    items = _inline(doc, folder, ".gif")
    for item in items:
        item["mode"] = item["key"].rpartition("_")[2].lstrip("0")
    return [item for item in items if not item["missing"]]          # a missing one is left out without a line


RENDER_WIDTH_PX = 480     # the render's frames, downscaled, as one animated WebP in the page
_RENDER_FOLDER = "derived/reconstruction/render"


def _render(folder: Path) -> dict | None:
    """The render's frames in `folder` as one animated WebP: {"n_frames", "src", "left_out"}; None without frames.
    Only the folder's own frames are read (`_own_file`); the others are named in left_out."""
    frames = sorted(folder.glob("frame_*.png")) if folder.is_dir() else []
    if not frames:
        return None
    from PIL import Image

    images, left_out = [], []
    for path in frames:
        own = _own_file(folder, path.name, _RENDER_FOLDER, "`odsplat render`")
        if isinstance(own, str):
            left_out.append(f"{path.name}: {own}")
            log.warning("report: render %s: %s; left out", path.name, own)
            continue
        try:
            data = _read_own(own)
        except OSError as e:
            left_out.append(f"{path.name}: could not be read ({e.strerror or e})")
            continue
        with Image.open(io.BytesIO(data)) as im:
            w, h = im.size
            scale = min(1.0, RENDER_WIDTH_PX / w)
            images.append(im.convert("RGB").resize((max(1, round(w * scale)), max(1, round(h * scale)))))
    if not images:
        return {"n_frames": 0, "src": None, "left_out": left_out}
    buf = io.BytesIO()
    images[0].save(buf, format="WEBP", save_all=True, append_images=images[1:], duration=120, loop=0, quality=80)
    return {"n_frames": len(images), "src": _data_uri("image/webp", buf.getvalue()), "left_out": left_out}


def render_video(folder: Path) -> str:
    """The reconstruction's magnified novel-view render (`odsplat render`'s frames in `folder`) as the report's
    section, inline as an animated WebP: browsers play it in the page, where they cannot play the mp4 this OpenCV
    build writes (MPEG-4 Part 2). Empty where there are no frames."""
    render = _render(folder)
    if render is None:
        return ""
    return str(_TEMPLATES.get_template("macros.html").module.render(render))


# ---------------------------------------------------------------------------------------------- the page

def capture_setup(capture: Capture) -> dict:
    """The setup in a few facts, from the capture and (where they ran) sync and poses: what the summary shows."""
    m = capture.manifest
    out = {"capture": capture.root.name}
    if m.daq_sample_rate_hz:
        out["DAQ"] = f"{m.daq_sample_rate_hz:g} Hz, {len(m.channels)} channels"
    if m.camera.fps:
        out["camera"] = f"{m.camera.fps:g} fps, {m.camera.width_px}x{m.camera.height_px} px, {m.camera.bit_depth} bit"
    try:

        sync = load_sync(capture)
        res = [abs(t.residual_frames) for t in sync.ok if t.residual_frames is not None]
        out["views synced"] = (f"{len(sync.ok)} of {len(sync.takes)}"
                               + (f", timing residual median {np.median(res):.3f} frame" if res else ""))
    except InputError:
        pass
    try:

        poses = PoseResult.read(capture)
        takes = [v for v in poses.views if v.kind == "take"]
        out["views posed"] = f"{len(takes)}"
        rms = [v.reproj_rms_px for v in takes if v.reproj_rms_px is not None]
        if rms:
            out["views posed"] += f", reprojection {float(np.median(rms)):.2f} px rms median ({poses.method})"
    except InputError:
        pass
    return out


def render_report(doc: dict, folder: Path, title: str, setup: dict | None = None,
                  render: dict | None = None) -> str:
    """The report's HTML from a loaded analysis.json (`folder` holds it and its plots); `setup`: facts of the
    capture for the summary (capture_setup); `render`: the render's frames (`_render`), where there are any."""
    return _TEMPLATES.get_template("report.html").render(
        title=str(doc.get("capture") or title), created=str(doc.get("created_utc", "(no date)")),
        n_sensors=len(_list(doc.get("sensors"))), n_averages=str(doc.get("n_averages", "?")),
        summary=_summary(doc, setup or {}), notes=_notes(doc), animations=_animations(doc, folder), render=render,
        hits=_hits(doc), modes=_modes(doc), video=_video(doc), correlation=_correlation(doc),
        figures=_inline(doc, folder, ".png"), settings=_settings(doc))


def write_report(capture: Capture) -> Path:
    """derived/analysis/report.html from derived/analysis/analysis.json and the plots it lists; returns its path."""
    doc = read_analysis(capture)
    path = capture.paths.report_html
    atomic_write_text(path, render_report(doc, capture.paths.analysis_dir, capture.root.name, capture_setup(capture),
                                          _render(capture.paths.render_dir)))
    log.info("report written to %s", path)
    return path
