"""A self-contained HTML report of an analysis (derived/analysis/analysis.json and its plots): one file, CSS and
images inline, that can be mailed.

analysis.json is data a user may edit by hand: it is read as the typed `AnalysisDocument` (analysis/document.py),
which refuses a field of the wrong kind in one line before anything is shown. Nothing in it reaches the page as
HTML: this module turns the document into plain text (numbers formatted, rows listed, flags for the CSS classes),
and the Jinja2 templates in `templates/` lay that out with every value escaped. Images are inlined only from files
the analysis itself wrote in its own folder (`_own_file`), read here and encoded here; a file name that leads
anywhere else is shown, escaped, with why it was left out."""
from __future__ import annotations

import html
import io
import logging
from pathlib import Path

import jinja2
import numpy as np
from markupsafe import Markup

from odsplat.reconstruction import PoseResult
from odsplat.spine.atomic import atomic_write_text
from odsplat.spine.errors import InputError
from odsplat.spine.store import Capture
from odsplat.sync import load_sync

from .clips import band_hz
from .document import (
    AnalysisDocument,
    ModeEntry,
    NoiseFloorSection,
    PairEntry,
    VideoSection,
    read_analysis,
)
from .pagekit import DASH
from .pagekit import MEDIA as _MEDIA
from .pagekit import SIGNATURES as _SIGNATURES
from .pagekit import data_uri as _data_uri
from .pagekit import finite as _finite
from .pagekit import index_in as _index
from .pagekit import num as _num
from .pagekit import own_file as _own_file
from .pagekit import read_own as _read_own
from .report_parts import caption, capture_takes, noise_part, shapes_part, takes_part
from .verdict import (
    DISCRIMINATION,
    FULL_FIELD_DISTINCT,
    NOT_DISCRIMINATED,
    ModeStatus,
    Verdict,
)
from .video2d import has_video2d, read_video2d

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


# ---------------------------------------------------------------------------------------------- plain values

def _mode_name(modes: tuple[ModeEntry, ...], k: int) -> str:
    """Mode k by number and frequency ("2 (31.00 Hz)"), or k as it stands where it names no mode."""
    i = _index(k, len(modes))
    return f"{i + 1} ({_num(modes[i].freq_hz, '.2f')} Hz)" if i is not None else str(k)


def _fitted_mode(fitted: tuple[int, ...], b: int) -> int:
    """The accelerometer mode the video's b-th fitted mode is (modes_fitted[b]); b itself where b indexes none."""
    i = _index(b, len(fitted))
    return fitted[i] if i is not None else b


# ---------------------------------------------------------------------------------------------- sections

def _summary(doc: AnalysisDocument, setup: dict) -> dict:
    """The page's top: the setup, the modes with their MAC, and the verdict line."""
    by_mode = doc.pair_by_mode()
    verdict = doc.correlation.verdict if doc.correlation is not None else None
    statuses = {s.mode: s for s in verdict.modes} if verdict is not None else {}
    rows = []
    grey = doc.not_judged()
    for k, m in enumerate(doc.modes):
        p = by_mode.get(k)
        st = statuses.get(k + 1)
        rows.append({"mode": str(k + 1), "freq": _num(m.freq_hz, ".2f"), "damping": _num(m.damping, ".2f", 100),
                     "mac": DASH if p is None else _num(p.mac, ".3f"), "grey": grey.get(k),
                     "scale": DASH if p is None else _num(p.scale_factor_abs, ".2f"),
                     "status": None if st is None else _status(st)})
    line = verdict.line if verdict is not None and verdict.line else None
    setup_rows = [[str(k), str(v)] for k, v in setup.items()]
    setup_rows += [["hits averaged", f"{doc.n_averages} of {len(doc.takes)}"], ["sensors", ", ".join(doc.sensors)],
                   ["fit band", f"{_num(doc.band_hz[0], '.0f')} to {_num(doc.band_hz[1], '.0f')} Hz"]]
    # no verdict (no video side, or none judged): the notes are there to read, not a failure
    css = _verdict(verdict)["css"] if verdict is not None and verdict.status in _CSS else ("warn" if doc.notes else "")
    return {"verdict": line, "css": css, "statuses": bool(statuses), "single": single_view_line(doc.sensor_view),
            "video": doc.video is not None, "n_modes": len(doc.modes), "n_notes": len(doc.notes),
            "setup": setup_rows, "modes": rows, "rests_on": _rests_on(doc)}


def _rests_on(doc: AnalysisDocument) -> str | None:
    """What the verdict rests on, in one sentence: the sensors, the video's points, the reference's AutoMAC."""
    parts = [f"{len(doc.sensors)} accelerometer direction{'s' if len(doc.sensors) != 1 else ''}"]
    if doc.video is not None:
        parts.append(f"the video's shapes at {doc.video.n_surface_points} surface points")
    auto = doc.correlation.reference_automac if doc.correlation is not None else None
    fitted = doc.video.modes_fitted if doc.video is not None else ()
    n = len(auto) if auto is not None else 0
    if n > 1 and all(len(row) == n for row in auto):     # square, as the analysis writes it (a hand edit may not be)
        a = np.array(auto, float)
        a[~np.isfinite(a) | np.eye(n, dtype=bool)] = np.nan
        if np.isfinite(a).any():
            i, j = np.unravel_index(np.nanargmax(a), a.shape)
            parts.append(f"the accelerometers' AutoMAC at most {a[i, j]:.2f} off the diagonal (modes "
                         f"{_fitted_mode(fitted, int(i)) + 1} and {_fitted_mode(fitted, int(j)) + 1}; above "
                         f"{DISCRIMINATION:g} the sensors cannot tell two modes apart)")
    return "Rests on " + ", ".join(parts) + "."


def single_view_line(sv: dict | None) -> str | None:
    """One sentence for the summary: the modes the single-view check judged, their MAC and scale, and how many it
    did not judge (sensorview.py); None without the check."""
    if not sv:
        return None
    judged = [m for m in sv["modes"] if m["judged"]]
    out = (f"One view against its accelerometers ({len(sv['sensors'])} in the image plane): "
           + ("; ".join(f"{m['label']} ({m['freq_hz']:.1f} Hz) MAC {m['mac']:.3f}, "
                        f"scale {m['scale']:.2f}" for m in judged) or "no mode judged"))
    rest = len(sv["modes"]) - len(judged)
    return out + (f"; {rest} not judged (below the floor, or hardly moving these sensors)." if rest else ".")


def _hits(doc: AnalysisDocument) -> dict:
    rejected = {h.take: list(h.reasons) for h in doc.rejected_hits}
    rows = [{"take": t, "used": t not in rejected, "reasons": "; ".join(rejected.get(t, []))} for t in doc.takes]
    rows += [{"take": t, "used": False, "reasons": "; ".join(r)} for t, r in rejected.items() if t not in doc.takes]
    return {"n_used": len([t for t in doc.takes if t not in rejected]), "n_takes": len(doc.takes),
            "averages": str(doc.n_averages), "tau_ms": _num(doc.exp_tau_s, ".3g", 1e3) if doc.exp_tau_s else None,
            "rows": rows}


def _background(v: VideoSection) -> dict | None:
    """The points left out of the shapes, and how much they move."""
    if not v.n_background_points:
        return None
    amplitude = None
    if v.background_amplitude_ratio is not None:
        amplitude = {"um": _num(v.background_amplitude_um, ".3g"), "n_reference": str(v.n_background_reference_points),
                     "ratio": _num(v.background_amplitude_ratio, ".1f", 100),
                     "ratio_all": _num(v.background_amplitude_ratio_all, ".1f", 100)}
    return {"rule": v.structure_rule, "n": str(v.n_background_points), "rms": _num(v.background_rms_um, ".3g"),
            "amplitude": amplitude}


def _video(doc: AnalysisDocument) -> dict | None:
    """The video side: what was fitted to the reconstruction's motion, its noise, its own poles and the 2D
    cross-check; None where the analysis has no video side."""
    v = doc.video
    if v is None:
        return None
    modes = doc.modes
    pairs = doc.correlation.pairs if doc.correlation is not None else ()
    out = {"fitted": ", ".join(_mode_name(modes, k) for k in v.modes_fitted) or "none",
           "surface": {"n": str(v.n_surface_points), "background": _background(v)},
           "window": [_num(v.window_s[0], ".1f", 1e3), _num(v.window_s[1], ".1f", 1e3)],
           "condition": _num(v.condition, ".3g"), "real": None, "r2": _sensor_rows(doc.sensors, v.sensor_r2),
           "poles": _poles(modes, v.freq_hz, v.damping, pairs), "image_poles": None, "noise": _noise(v.noise_floor),
           "crosscheck": [], "limit": _limit(modes, v.physical_limit), "triangulation": None}
    if v.real_modes:
        ratios = [r for r in (_finite(m.quadrature_over_noise) for m in v.real_modes if m.real) if r is not None]
        out["real"] = {"n_real": sum(m.real for m in v.real_modes), "n": len(v.real_modes),
                       "ratios": [_num(min(ratios), ".2f"), _num(max(ratios), ".2f")] if ratios else None}
    im = doc.image_poles
    if im is not None:
        out["image_poles"] = {"n_views": str(im.n_views), "n_pixels": str(im.n_pixels),
                              "window": [_num(im.window_s[0], ".1f", 1e3), _num(im.window_s[1], ".1f", 1e3)],
                              **_poles(modes, im.freq_hz, im.damping, pairs)}
    tri = getattr(v, "triangulation", None)
    if tri:
        out["triangulation"] = {
            "n_points": str(tri["n_points"]), "n_views": str(tri["n_views"]),
            "views": _num(tri["views_per_point"], ".0f"), "gain": _num(tri["gain"], ".2f"),
            "correlation": _num(tri["correlation"], ".2f"), "motion": _num(tri["motion_rms_um"], ".3g"),
            "motion_px": _num(tri.get("motion_px"), ".3g"), "noise_px": _num(tri.get("noise_px"), ".2g"),
            "expected": _num(tri.get("expected_correlation"), ".2f"),
            "modes": [[_num(m["freq_hz"], ".1f"), _num(m["mac"], ".3f"), _num(m["scale"], ".2f")]
                      for m in tri["modes"]]}
    if v.crosscheck:
        out["crosscheck_verdict"] = _verdict(v.crosscheck_verdict)
        out["crosscheck"] = [[c.take, str(c.n_points), _num(c.gain, ".2f"), _num(c.correlation, ".2f"),
                              _num(c.motion_rms_px, ".3f"), _num(c.noise_px, ".4f"), _num(c.force_ratio, ".2f")]
                             for c in v.crosscheck]
    return out


_CSS = {"met": "ok", "not met": "bad", NOT_DISCRIMINATED: "warn"}   # a status's colour; any other: grey


def _verdict(v: Verdict | None) -> dict | None:
    """A verdict's line and status, with the CSS class of its colour."""
    if v is None:
        return None
    return {"css": _CSS.get(v.status, "meta"), "status": v.status, "line": v.line}


def _status(s: ModeStatus) -> dict:
    """A mode's status under the MAC target: its name, colour and words."""
    return {"status": s.status, "css": _CSS.get(s.status, "meta"), "text": s.text}


def _limit(modes: tuple[ModeEntry, ...], pl: dict | None) -> dict | None:
    """The physical limit (analysis/crlb.py `physical_limit`): the bound against the floor, per point and mode."""
    if not pl:
        return None
    noise = pl.get("noise") or {}
    words = (f"gain {_num(noise.get('gain_dn_per_e'), '.3g')} DN per electron, read noise "
             f"{_num(noise.get('read_dn'), '.3g')} DN, {noise.get('frames', 0)} frames"
             if noise.get("measured") else "quantisation only: too few frames at rest")
    rows = []
    for m in pl.get("modes", ()):
        k = next((i for i, e in enumerate(modes) if abs(e.freq_hz - m["freq_hz"]) < 1e-6 * m["freq_hz"]), None)
        limit = m.get("limit") or ""
        rows.append({"name": f"{k + 1} ({m['freq_hz']:.2f} Hz)" if k is not None else f"{m['freq_hz']:.2f} Hz",
                     "floor": _num(m.get("floor_um"), ".3g"), "bound": _num(m.get("bound_floor_um"), ".3g"),
                     "ratio": _num(m.get("ratio"), ".2g"), "limit": limit.partition(": ")[2] or limit})
    return {"noise": words, "bound": _num(pl.get("bound_um"), ".3g"), "single": _num(pl.get("single_view_um"), ".3g"),
            "measured": _num(pl.get("measured_um"), ".3g"), "ratio": _num(pl.get("ratio"), ".2g"),
            "views": _num(pl.get("median_views"), ".0f"), "unresolved": pl.get("n_unresolved") or 0,
            "modes": rows, "direction": list(pl.get("direction_lines", ()))}


def _noise(nf: NoiseFloorSection | None) -> dict | None:
    """The video's noise floor: where it was measured, and in metres."""
    if nf is None:
        return None
    k = _finite(nf.floor_sigmas)
    at_floor = nf.floor_mac if nf.floor_mac is not None else (k * k / (k * k + 1) if k is not None else None)
    return {"sigma": _num(nf.sigma_um, ".3g"),
            "static": ({"n": str(nf.n_static_points), "sigma": _num(nf.static_sigma_um, ".3g")}
                       if nf.n_static_points else None),
            "pre_impact": ({"n": str(nf.n_pre_impact), "sigma": _num(nf.pre_impact_sigma_um, ".3g")}
                           if nf.pre_impact_sigma_um is not None else None),
            "sigmas": _num(nf.floor_sigmas, ".3g"), "mac": _num(at_floor, ".2f")}


def _products(modes: tuple[ModeEntry, ...], pairs: tuple[PairEntry, ...]) -> list[tuple[float, str]]:
    """The second-order products of the video's two strongest modes (by their video amplitude): twice each, their
    sum and their difference, with names. A camera's intensity is not quite linear in the motion, so the strongest
    motion leaves a little energy there, and a pole finder can find it."""
    amps = {}
    for p in pairs:
        k, a = _index(p.a, len(modes)), _finite(p.video_amplitude_um)
        if k is not None and a is not None:
            amps[k] = a
    top = sorted(amps, key=lambda k: -amps[k])[:2]
    f = {k: modes[k].freq_hz for k in top}
    out = [(2 * f[k], f"2 x mode {k + 1}") for k in top]
    if len(top) == 2:
        a, b = top
        out += [(f[a] + f[b], f"mode {a + 1} + mode {b + 1}"), (abs(f[a] - f[b]), f"mode {a + 1} - mode {b + 1}")]
    return out


def _poles(modes: tuple[ModeEntry, ...], fv: tuple[float, ...], zv: tuple[float, ...],
           pairs: tuple[PairEntry, ...]) -> dict:
    """The camera's own poles against the nearest accelerometer mode; one more than 1 % from every mode is said to
    be no mode of theirs, and named where it lies near a product of the strongest motion (`_products`)."""
    fa = np.array([_finite(m.freq_hz) or np.nan for m in modes], float)
    products = _products(modes, pairs)
    rows = []
    for i, x in enumerate(fv):
        f = _finite(x)
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


def _poles_table(modes: tuple[ModeEntry, ...], fv: tuple[float, ...], zv: tuple[float, ...], title: str, empty: str,
                 pairs: tuple[PairEntry, ...] = ()) -> str:
    """One table of poles (`_poles`) as the page lays it out, under `title` (the line `empty` where there are none)."""
    macros = _TEMPLATES.get_template("macros.html").module
    return str(macros.poles_table(_poles(modes, fv, zv, pairs), title, empty))


def _sensor_rows(sensors: tuple[str, ...], values: tuple[float, ...]) -> list[list[str]]:
    """One value per sensor (named, or numbered where the document has fewer names)."""
    return [[sensors[j] if j < len(sensors) else f"sensor {j + 1}", _num(x, ".3f")] for j, x in enumerate(values)]


def _correlation(doc: AnalysisDocument) -> dict:
    c = doc.correlation
    modes = doc.modes
    fitted = doc.video.modes_fitted if doc.video is not None else ()
    out = {"pairs": None, "verdict": None, "comac": [], "ods": [], "statuses": [], "matrices": []}
    nf = doc.video.noise_floor if doc.video is not None else None
    apart = {k for k, e in enumerate(nf.modes if nf is not None else ()) if e.not_separated}
    if c is not None:
        out["pairs"] = [{"a": _mode_name(modes, _fitted_mode(fitted, p.a)),
                         "b": _mode_name(modes, _fitted_mode(fitted, p.b)),
                         "mac": _num(p.mac, ".3f"), "below": p.below_noise_floor is True,
                         "apart": p.b in apart,
                         "expected": _num(p.expected_mac, ".3f"), "amplitude": _num(p.video_amplitude_um, ".3g"),
                         "floor": _num(p.noise_floor_um, ".3g"), "scale": _num(p.scale_factor_abs, ".3g"),
                         "phase": _num(p.scale_factor_phase_deg, "+.1f"), "freq_a": _num(p.freq_a_hz, ".2f"),
                         "freq_b": _num(p.freq_b_hz, ".2f"), "diff": _num(p.freq_diff_rel, "+.2f", 100)}
                        for p in c.pairs]
        out["verdict"] = _verdict(c.verdict)
        out["comac"] = _sensor_rows(doc.sensors, c.comac)
        out["statuses"] = [{"mode": _mode_name(modes, s.mode - 1) if _index(s.mode - 1, len(modes)) is not None
                            else str(s.mode), **_status(s)}
                           for s in (c.verdict.modes if c.verdict is not None else ())]
        out["matrices"] = _matrices(doc)
    out["ods"] = [[str(i + 1), _num(o.freq_hz, ".2f"), _num(o.mac, ".3f")] for i, o in enumerate(doc.ods)]
    return out


def _heat(x: float | None) -> str:
    """The CSS class of a MAC cell's shade: h0 (0-0.1) to h9 (0.9-1); none where it is no finite number."""
    v = _finite(x)
    return "" if v is None else f"h{min(9, max(0, int(v * 10)))}"


def _matrix(title: str, note: str, values, rows: list[str], cols: list[str], mark: float | None) -> dict | None:
    """A MAC matrix as a small table whose cells are shaded by value: rows and cols name the modes; off the
    diagonal a value above `mark` is outlined (modes alike there). None where the document holds none."""
    if values is None:
        return None
    n_cols = max([len(cols)] + [len(r) for r in values])
    cells = []
    for i, row in enumerate(values):
        line = []
        for j in range(n_cols):
            x = _finite(row[j]) if j < len(row) else None
            over = mark is not None and i != j and x is not None and x > mark
            line.append({"v": _num(x, ".2f"), "css": (_heat(x) + (" over" if over else "")).strip()})
        cells.append({"label": rows[i] if i < len(rows) else str(i + 1), "cells": line})
    return {"title": title, "note": note, "cols": [cols[j] if j < len(cols) else str(j + 1) for j in range(n_cols)],
            "rows": cells}


def _matrices(doc: AnalysisDocument) -> list[dict]:
    """The MAC matrix (accelerometers against video), the reference's AutoMAC at the sensors and the video's
    full-field cross-MAC, each mode named by its number (the pairs' indices are the video's fitted modes)."""
    c = doc.correlation
    fitted = doc.video.modes_fitted if doc.video is not None else ()
    n = max([len(m) for m in (c.mac_matrix, c.reference_automac, c.video_cross_mac) if m is not None] + [0])
    names = [str(_fitted_mode(fitted, i) + 1) for i in range(n)]
    out = [_matrix("MAC: accelerometers (rows) vs video (columns)", "at the sensors", c.mac_matrix,
                   [f"a {x}" for x in names], [f"b {x}" for x in names], None),
           _matrix("AutoMAC, accelerometers", f"at the sensors; outlined: above {DISCRIMINATION:g}, the sensors "
                   "cannot tell the two modes apart", c.reference_automac, names, names, DISCRIMINATION),
           _matrix("Cross-MAC, video full field", f"over every surface point; outlined: above "
                   f"{FULL_FIELD_DISTINCT:g}, the video does not tell the two apart", c.video_cross_mac, names, names,
                   FULL_FIELD_DISTINCT)]
    return [m for m in out if m is not None]


# ---------------------------------------------------------------------------------------------- inlined files

def _inline(doc: AnalysisDocument, folder: Path, suffix: str) -> list[dict]:
    """Each output file of the analysis ending in `suffix`, as {"key", "file", "src"} with its data: URI, or with
    "problem" (one line naming the file) where it is missing ("missing" set) or is no file of the analysis's own
    in `folder`, or no image of its kind."""
    out = []
    for key, rel in doc.files.items():
        if not rel.lower().endswith(suffix):
            continue
        item = {"key": key, "file": rel, "src": None, "problem": None, "missing": False}
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


def _animations(doc: AnalysisDocument, folder: Path) -> list[dict]:
    """The modes in motion: each animation inline (a GIF in the page itself), captioned with its mode's number."""
    items = _inline(doc, folder, ".gif")
    for item in items:
        item["mode"] = item["key"].rpartition("_")[2].lstrip("0")
    return [item for item in items if not item["missing"]]          # a missing one is left out without a line


RENDER_WIDTH_PX = 480     # the render's frames, downscaled, as one animated WebP in the page
_RENDER_FOLDER = "derived/reconstruction/render"


MAX_INLINE_VIDEO_BYTES = 16 * 2**20     # an mp4 larger than this is not inlined (the render's shows as its frames)


def _inline_mp4(folder: Path, name: str, where: str, writer: str) -> tuple[str | None, str]:
    """The folder's own mp4 `name` (`_own_file`) as a data: URI and ""; or None and why not ("not found", not the
    folder's own, too large to inline, unreadable)."""
    own = _own_file(folder, name, where, writer)
    if isinstance(own, str):
        return None, own
    if own.stat().st_size > MAX_INLINE_VIDEO_BYTES:
        return None, f"larger than {MAX_INLINE_VIDEO_BYTES // 2**20} MB, not inlined"
    try:
        return _data_uri("video/mp4", _read_own(own)), ""
    except OSError as e:
        return None, f"could not be read ({e.strerror or e})"


def _render_mp4(folder: Path, n_frames: int) -> dict | None:
    """The render's H.264 mp4 (render.mp4 in `folder`) inline as a video: {"n_frames", "video", "left_out"}; None
    where there is none, or it cannot be inlined (`_inline_mp4`)."""
    video, _ = _inline_mp4(folder, "render.mp4", _RENDER_FOLDER, "odsplat render")
    return None if video is None else {"n_frames": n_frames, "src": None, "video": video, "left_out": []}


def _render(folder: Path) -> dict | None:
    """The render inline: its mp4 as a video where there is one small enough (`_render_mp4`), else its frames as one
    animated WebP: {"n_frames", "src", "video", "left_out"}; None without frames. Only the folder's own files are
    read (`_own_file`); the others are named in left_out."""
    frames = sorted(folder.glob("frame_*.png")) if folder.is_dir() else []
    if not frames:
        return None
    video = _render_mp4(folder, len(frames))
    if video is not None:
        return video
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
        return {"n_frames": 0, "src": None, "video": None, "left_out": left_out}
    buf = io.BytesIO()
    images[0].save(buf, format="WEBP", save_all=True, append_images=images[1:], duration=120, loop=0, quality=80)
    return {"n_frames": len(images), "src": _data_uri("image/webp", buf.getvalue()), "video": None,
            "left_out": left_out}


def render_video(folder: Path) -> str:
    """The reconstruction's magnified novel-view render (`odsplat render`'s frames in `folder`) as the report's
    section, inline (its mp4, or its frames as an animated WebP). Empty where there are no frames."""
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


def _sensor_view(sv: dict | None) -> dict | None:
    """One view against the accelerometers it sees (sensorview.SensorView.document, in analysis.json or
    video2d.json) as the report's rows; None where the analysis has no such check."""
    if not sv:
        return None
    sensors = [[s["name"], f"{s['pixel_px'][0]:.0f}, {s['pixel_px'][1]:.0f}", _num(s["px_per_m"], ".0f"),
                _num(s["tilt_deg"], ".0f"), str(s["n_windows"]), _num(s["r2"], ".2f"), _num(s["noise_um"], ".3g")]
               for s in sv["sensors"]]
    modes = []
    for m in sv["modes"]:
        modes.append({"css": "" if m["judged"] else "grey",
                      "cells": [m["label"], _num(m["freq_hz"], ".2f"), _num(m["mac"], ".3f"), _num(m["scale"], ".2f"),
                                _num(m["scale_phase_deg"], "+.0f"), _num(m["expected_mac"], ".3f"), m["state"]]})
    decay = sv["method"] == "decay"
    how = ("each mode's residues (m/N) from the same decay fit at the accelerometers' poles" if decay else
           "each mode's shape from one FDD of the readings and the accelerometers (one phase, the accelerometers in "
           "metres) at the 2D path's modes")
    return {"view": str(sv["view"]), "n_takes": str(len(sv["takes"])), "pose": sv["pose"], "sensors": sensors,
            "how": how, "left_out": [(s["name"], s["why"]) for s in sv["left_out"]], "modes": modes}


_CLIPS_FOLDER = "derived/mode_clips"


def mode_clips(capture: Capture, n_modes: int) -> dict[int, dict]:
    """Each mode's amplified clip the report stage rendered (derived/mode_clips/, `odsplat.app.report`), inline:
    {mode number: {"src", "caption"}}, or {"src": None, "caption": why} where one is there but cannot be shown.
    Only the folder's own files are read (`_own_file`)."""
    folder = capture.paths.mode_clips_dir
    out: dict[int, dict] = {}
    if not folder.is_dir():
        return out
    for k in range(1, n_modes + 1):
        name = capture.paths.mode_clip(k).name
        src, why = _inline_mp4(folder, name, _CLIPS_FOLDER, "the report stage")
        if why == "not found":
            continue
        if src is None:
            log.warning("report: %s/%s: %s; left out", _CLIPS_FOLDER, name, why)
        out[k] = {"src": src, "caption": (f"mode {k} on the reconstruction's Gaussians through one cycle, magnified "
                                          "so that its largest motion is 5 % of the structure's size (the factor "
                                          "is on the clip)") if src else f"{_CLIPS_FOLDER}/{name}: {why}"}
    return out


def render_report(doc: AnalysisDocument, folder: Path, title: str, setup: dict | None = None,
                  render: dict | None = None, takes: dict[str, dict] | None = None,
                  clips: dict[int, dict] | None = None) -> str:
    """The report's HTML from a loaded analysis.json (`folder` holds it and its plots); `setup`: facts of the
    capture for the summary (capture_setup); `render`: the render's frames (`_render`), where there are any;
    `takes`: the capture's takes and their QC (report_parts.capture_takes), for the takes left out; `clips`: each
    mode's amplified clip (`mode_clips`)."""
    summary = _summary(doc, setup or {})
    shapes = shapes_part(doc, folder)
    gifs = {a["mode"]: a for a in _animations(doc, folder)}
    for md in shapes["modes"]:                 # a GIF only where the page has no 3D shape of the mode
        md["gif"] = None if md["shape"] else gifs.get(md["mode"])
        md["clip"] = (clips or {}).get(int(md["mode"]))
    figures = _inline(doc, folder, ".png")
    for f in figures:
        f["caption"] = caption(doc, f["key"])
    frf = next((f for f in figures if f["key"] == "frf"), None)
    pairs = doc.correlation.pairs if doc.correlation is not None else ()
    fitted = doc.video.modes_fitted if doc.video is not None else ()
    noise = noise_part(doc, pairs, lambda p: _mode_name(doc.modes, _fitted_mode(fitted, p.b)))
    return _TEMPLATES.get_template("report.html").render(
        title=doc.capture or title, created=doc.created_utc or "(no date)", n_sensors=len(doc.sensors),
        n_averages=str(doc.n_averages), summary=summary, notes=list(doc.notes), takes=takes_part(doc, takes),
        frf=frf, shapes=shapes, render=render, hits=_hits(doc), video=_video(doc),
        noise=noise, sensor_view=_sensor_view(doc.sensor_view), correlation=_correlation(doc),
        figures=[f for f in figures if f["key"] != "frf"], settings=doc.settings_text() if doc.settings else None)


# ---------------------------------------------------------------------------------------------- the 2D path's page

def _own_uri(folder: Path, rel: str | None) -> str | None:
    """A file the 2D path wrote in `folder` as a data: URI (`_own_file`, `_read_own`); None where there is none or it
    is not one of the folder's own."""
    path = _own_file(folder, rel) if rel else None
    return _data_uri(_MEDIA[path.suffix], _read_own(path)) if isinstance(path, Path) else None


def _speed(fps: float) -> str:
    """How a clip played at 30 fps runs against the filming."""
    if fps > 30.5:
        return f"{fps / 30.0:.3g}x slower than filmed"
    return "the speed filmed" if fps > 29.5 else f"{30.0 / fps:.3g}x faster than filmed"


def _rows_2d(doc: dict, folder: Path) -> list[dict]:
    files = doc.get("files", {})
    rows = []
    for k, m in enumerate(doc["modes"], 1):
        amp = f"{m['amplitude_px']:.3g} px"
        if m.get("amplitude_m") is not None:
            amp += f" ({1e6 * m['amplitude_m']:.3g} µm)"
        z = f"{100 * m['damping']:.2f}" if m.get("damping") is not None else "FDD peak, no pole: an ODS"
        lo, hi = band_hz(m["freq_hz"], doc["fps"])
        rows.append(dict(k=k, f=f"{m['freq_hz']:.3f}", z=z, mpc=f"{m['mpc']:.2f}", amp=amp,
                         floor=f"{m['floor_mac']:.3f}", above=m["above_floor"],
                         state="above the floor" if m["above_floor"] else "below the floor: shape not judged",
                         shape=_own_uri(folder, files.get(f"shape_{k:02d}")), clip=_own_uri(folder, m.get("clip")),
                         band=f"{lo:.4g}-{hi:.4g}", alpha=f"{m['clip_alpha']:.0f}" if m.get("clip_alpha") else "",
                         title="Mode" if m.get("kind", "mode") == "mode" else "FDD peak", slow=_speed(doc["fps"])))
    return rows


def render_video2d_report(capture: Capture) -> str:
    """The report of a capture without force: its setup, the mode table (modes below the floor in grey, saying so),
    the spectrum, each mode's shape on the frame and amplified clip, the stabilisation chart; every figure and clip
    inlined, so the page stands alone (templates/video2d.html)."""
    doc, _ = read_video2d(capture)
    folder = capture.paths.analysis_dir
    files = doc.get("files", {})
    scale = doc.get("scale_m_per_px")
    setup = [("capture", doc["capture"]),
             ("take", doc["take"] + ("" if doc.get("view") is None else f" (view {doc['view']})")),
             ("frames", f"{doc['n_frames']} at {doc['fps']:g} fps ({doc['n_frames'] / doc['fps']:.3g} s)"),
             ("points", f"{doc['n_moving']} of {doc['n_points']} tracked move above their noise ({doc['tracker']} "
                        f"tracker, {doc['window_px']} px window)"),
             ("band", "-" if not doc.get("band_hz") else f"{doc['band_hz'][0]:.4g}-{doc['band_hz'][1]:.4g} Hz"),
             ("scale", f"{1e3 * scale:.4g} mm/px" if scale else "none given: motion in pixels"),
             ("noise floor", "-" if doc.get("noise_px_median") is None else
              f"{doc['noise_px_median']:.3g} px rms per moving point over the band (median), "
              f"{doc['noise_over_crlb_median']:.2g}x its Cramér-Rao bound of {doc['crlb_px_median']:.3g} px "
              f"(one frame; camera noise: {doc.get('camera_noise', '?')})")]
    single = single_view_line(doc.get("sensor_view"))
    if single:
        setup.append(("accelerometers", single))
    return _TEMPLATES.get_template("video2d.html").render(
        title=doc["capture"], created=doc.get("created_utc", ""), setup=setup, modes=_rows_2d(doc, folder),
        floor_mac=doc["floor_mac"], notes=doc.get("notes", []), spectrum=_own_uri(folder, files.get("spectrum")),
        stabilisation=_own_uri(folder, files.get("stabilisation")), sensor_view=_sensor_view(doc.get("sensor_view")))



def write_report(capture: Capture) -> Path:
    """derived/analysis/report.html from derived/analysis/analysis.json and the plots it lists (a capture without
    force: from video2d.json, `render_video2d_report`); returns its path."""
    path = capture.paths.report_html
    if not capture.manifest.has_force and has_video2d(capture):   # the 2D path's result (video only)
        atomic_write_text(path, render_video2d_report(capture))
        log.info("report written to %s", path)
        return path
    doc = read_analysis(capture)
    atomic_write_text(path, render_report(doc, capture.paths.analysis_dir, capture.root.name, capture_setup(capture),
                                          _render(capture.paths.render_dir), capture_takes(capture),
                                          mode_clips(capture, len(doc.modes))))
    log.info("report written to %s", path)
    return path
