"""A self-contained HTML report of an analysis (derived/analysis/analysis.json and its plots): one file, CSS and
images inline, that can be mailed."""
from __future__ import annotations

import base64
import io
import json
import logging
from html import escape
from pathlib import Path

import numpy as np

from odsplat.contract import check
from odsplat.errors import InputError
from odsplat.manifest import load_json
from odsplat.store import Capture, atomic_write_text

from .analyze import KIND, SCHEMA

log = logging.getLogger(__name__)


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>odsplat analysis: {title}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1100px; color: #222; padding: 0 1em; }}
h1 {{ font-size: 1.6em; margin-bottom: 0.2em; }} h2 {{ border-bottom: 1px solid #ccc; margin-top: 1.6em; }}
.meta {{ color: #666; }} .bad {{ color: #b00; }} .ok {{ color: #070; }}
table {{ border-collapse: collapse; margin: 0.6em 0; font-size: 0.95em; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.7em; text-align: right; }}
th {{ background: #f2f2f2; }} td.t {{ text-align: left; }}
figure {{ margin: 1em 0; }} figure img {{ max-width: 100%; border: 1px solid #ddd; }}
figcaption {{ color: #555; font-size: 0.9em; }} pre {{ background: #f7f7f7; padding: 0.6em; overflow-x: auto; }}
</style></head>
<body>
<h1>Analysis of {title}</h1>
<p class="meta">created {created} &middot; {n_sensors} sensors &middot; {n_avg} hits averaged</p>
{sections}
</body></html>
"""


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


# ---------------------------------------------------------------------------------------------- formatting

def _num(x, fmt: str = ".3g", scale: float = 1.0) -> str:
    try:
        v = float(x) * scale
    except (TypeError, ValueError):
        return "&ndash;"
    if not np.isfinite(v):
        return "&ndash;"
    text = format(v, fmt)
    return format(0.0, fmt) if float(text) == 0 else text      # no "-0.0"


def _table(head: list[str], rows: list[list[str]], text_cols: int = 1) -> str:
    """Cells are HTML already (escape text with `escape` first); the first text_cols columns align left."""
    h = "".join(f"<th>{c}</th>" for c in head)
    body = "".join("<tr>" + "".join(f'<td class="t">{c}</td>' if i < text_cols else f"<td>{c}</td>"
                                    for i, c in enumerate(r)) + "</tr>" for r in rows)
    return f"<table>{f'<tr>{h}</tr>' if any(head) else ''}{body}</table>"


def _mode_name(modes: list[dict], k) -> str:
    try:
        return f"{int(k) + 1} ({float(modes[int(k)]['freq_hz']):.2f} Hz)"
    except (TypeError, ValueError, IndexError):
        return escape(str(k))


# ---------------------------------------------------------------------------------------------- sections

def _reasons(r) -> list[str]:
    return [r] if isinstance(r, str) else [str(x) for x in r] if isinstance(r, list) else []


def _hits(doc: dict) -> str:
    takes = [str(t) for t in doc.get("takes", [])]
    rejected = {str(r.get("take")): _reasons(r.get("reasons")) for r in doc["rejected_hits"] if isinstance(r, dict)}
    used = [t for t in takes if t not in rejected]
    out = [f"<h2>Hits</h2><p>{len(used)} of {len(takes)} hits used"
           + (f" (averages: {escape(str(doc['n_averages']))})" if "n_averages" in doc else "") + "."]
    if doc.get("exp_tau_s"):
        out.append(f" Exponential window &tau; = {_num(doc['exp_tau_s'], '.3g', 1e3)} ms"
                   " (its damping is taken out of the modes).")
    out.append("</p>")
    rows = [[escape(t), '<span class="ok">used</span>' if t not in rejected else '<span class="bad">rejected</span>',
             escape("; ".join(rejected.get(t, [])))] for t in takes]
    rows += [[escape(t), '<span class="bad">rejected</span>', escape("; ".join(r))]
             for t, r in rejected.items() if t not in takes]
    if rows:
        out.append(_table(["take", "hit", "reasons"], rows, text_cols=3))
    return "".join(out)


def _modes(doc: dict) -> str:
    rows = [[str(k + 1), _num(m["freq_hz"], ".2f"), _num(m["damping"], ".2f", 100)] for k, m in enumerate(doc["modes"])]
    band = doc.get("band_hz")
    where = (f"<p>Fitted in {float(band[0]):.0f} to {float(band[1]):.0f} Hz.</p>"
             if isinstance(band, list) and len(band) == 2 else "")
    return "<h2>Modes (accelerometers)</h2>" + where + _table(["mode", "frequency (Hz)", "damping (%)"], rows)


def _notes(doc: dict) -> str:
    """What the numbers cannot show, at the top: peaks with no mode, a band that cuts a peak, missing geometry."""
    notes = [str(n) for n in doc.get("notes") or []]
    if not notes:
        return ""
    return "<h2>Notes</h2><ul>" + "".join(f'<li class="bad">{escape(n)}</li>' for n in notes) + "</ul>"


def _video(doc: dict) -> str:
    v = doc.get("video")
    if not v:
        return "<h2>Video</h2><p>No video side in this analysis.</p>"
    modes = doc["modes"]
    fitted = v.get("modes_fitted", [])
    out = ["<h2>Video</h2><p>Modes fitted to the video's motion with the accelerometer poles: "
           + (", ".join(_mode_name(modes, k) for k in fitted) or "none")]
    if "n_surface_points" in v:
        out.append(f"; {int(v['n_surface_points'])} surface points on the structure")
        if v.get("n_background_points"):
            out.append(f" ({escape(str(v.get('structure_rule', '')))}); the {int(v['n_background_points'])} "
                       f"points of the background (floor, base) are left out of the shapes, and move "
                       f"{_num(v.get('background_rms_um'), '.3g')} &micro;m rms: the video's noise in the open")
            if v.get("background_amplitude_ratio") is not None:
                out.append(f". In the modes above the noise floor the background reads "
                           f"{_num(v.get('background_amplitude_um'), '.3g')} &micro;m (median, the "
                           f"{int(v.get('n_background_reference_points', 0))} points seen by as many views as the "
                           f"structure), {_num(v['background_amplitude_ratio'], '.1f', 100)} % of the structure's "
                           f"median amplitude ({_num(v.get('background_amplitude_ratio_all'), '.1f', 100)} % over "
                           "the whole background): the shapes' noise against their motion")
    if "window_s" in v and len(v["window_s"]) == 2:
        out.append(f"; window {_num(v['window_s'][0], '.1f', 1e3)} to {_num(v['window_s'][1], '.1f', 1e3)} ms")
    if "condition" in v:
        out.append(f"; condition number {_num(v['condition'], '.3g')}")
    real = [m for m in v.get("real_modes") or [] if isinstance(m, dict)]
    if real:
        n_real = sum(bool(m.get("real")) for m in real)
        ratios = [float(m["quadrature_over_noise"]) for m in real
                  if m.get("real") and isinstance(m.get("quadrature_over_noise"), (int, float))]
        if n_real:
            out.append(f". {n_real} of {len(real)} mode shapes are real (normal) modes, each on its common phase: "
                       "what lay out of phase was noise"
                       + (f" ({_num(min(ratios), '.2f')}-{_num(max(ratios), '.2f')} x the noise's energy there)"
                          if ratios else "")
                       + ", so half the noise's power is gone from them"
                       + ("; the others are complex and kept as fitted (notes)" if n_real < len(real) else ""))
        else:
            out.append(". No mode shape is real within the noise: all are kept complex, as fitted (notes)")
    out.append(".</p>")
    sensors = [str(s) for s in doc.get("sensors", [])]
    r2 = v.get("sensor_r2", [])
    if r2:
        out.append("<p>Share of each sensor point's video motion that these modes explain (r&sup2;):</p>")
        out.append(_sensor_table(sensors, "r&sup2;", r2))
    corr = doc.get("correlation")
    pairs = corr.get("pairs", []) if isinstance(corr, dict) else []
    out.append(_poles_table(modes, v.get("freq_hz", []), v.get("damping", []),
                            "Poles found in the reconstruction's motion alone (matrix pencil, stable over ranks)",
                            "No pole was found stable in the reconstruction's motion alone.", pairs))
    im = doc.get("image_poles")
    if isinstance(im, dict):
        window = im.get("window_s") or [None, None]
        out.append(_poles_table(modes, im.get("freq_hz", []), im.get("damping", []),
                                f"Poles found in the raw frames alone ({int(im.get('n_views', 0))} views, "
                                f"{int(im.get('n_pixels', 0))} pixels, {_num(window[0], '.1f', 1e3)} to "
                                f"{_num(window[-1], '.1f', 1e3)} ms; matrix pencil)",
                                "No pole was found stable in the raw frames alone.", pairs))
    out.append(_noise(v))
    checks = v.get("crosscheck") or []
    if checks:
        out.append("<p>The 3D motion projected into single views against 2D tracks of their raw frames "
                   "(gain 1: the reconstruction moves as much as the images show):</p>")
        out.append(_verdict(v.get("crosscheck_verdict")))
        out.append(_table(["take", "points", "gain", "correlation", "motion rms (px)", "track noise (px)",
                           "impulse ratio"],
                          [[escape(str(c.get("take", ""))), str(c.get("n_points", "")), _num(c.get("gain"), ".2f"),
                            _num(c.get("correlation"), ".2f"), _num(c.get("motion_rms_px"), ".3f"),
                            _num(c.get("noise_px"), ".4f"), _num(c.get("force_ratio"), ".2f")] for c in checks]))
    return "".join(out)


def _verdict(v) -> str:
    """A verdict's line, coloured by its status."""
    if not isinstance(v, dict) or "line" not in v:
        return ""
    status = str(v.get("status", ""))
    css = {"met": "ok", "not met": "bad"}.get(status, "meta")
    return f'<p class="{css}"><b>Verdict ({escape(status)}):</b> {escape(str(v["line"]))}</p>'


def _noise(v: dict) -> str:
    """The video's noise floor: where it was measured, and in metres."""
    nf = v.get("noise_floor")
    if not isinstance(nf, dict):
        return ""
    parts = [f"the motion the modes do not explain, {_num(nf.get('sigma_um'), '.3g')} &micro;m per point and "
             "timestep (median over the points)"]
    if nf.get("n_static_points"):
        parts.append(f"{int(nf['n_static_points'])} static points (the modes explain none of their motion): "
                     f"{_num(nf.get('static_sigma_um'), '.3g')} &micro;m")
    if nf.get("pre_impact_sigma_um") is not None:
        parts.append(f"{int(nf.get('n_pre_impact', 0))} timesteps before the impact: "
                     f"{_num(nf.get('pre_impact_sigma_um'), '.3g')} &micro;m")
    k = nf.get("floor_sigmas")
    at_floor = nf.get("floor_mac", k * k / (k * k + 1) if isinstance(k, (int, float)) else None)  # older files
    return ("<p>The video's noise floor, measured where nothing moves: " + "; ".join(parts)
            + f". A mode needs {_num(k, '.3g')} noise standard deviations of amplitude at the sensors (the noise then "
            f"allows its complex shape a MAC of {_num(at_floor, '.2f')}; a real mode's shape keeps half the noise's "
            "power, so it reads at or above what this allows) to be judged; the correlation table gives each "
            "mode's.</p>")


def _products(modes: list[dict], pairs: list[dict]) -> list[tuple[float, str]]:
    """The second-order products of the video's two strongest modes (by their video amplitude): twice each, their
    sum and their difference, with names. A camera's intensity is not quite linear in the motion, so the strongest
    motion leaves a little energy there, and a pole finder can find it."""
    amps = {int(p["a"]): float(p["video_amplitude_um"]) for p in pairs
            if isinstance(p, dict) and isinstance(p.get("video_amplitude_um"), (int, float)) and "a" in p}
    top = sorted((k for k in amps if 0 <= k < len(modes)), key=lambda k: -amps[k])[:2]
    f = {k: float(modes[k]["freq_hz"]) for k in top}
    out = [(2 * f[k], f"2 x mode {k + 1}") for k in top]
    if len(top) == 2:
        a, b = top
        out += [(f[a] + f[b], f"mode {a + 1} + mode {b + 1}"), (abs(f[a] - f[b]), f"mode {a + 1} - mode {b + 1}")]
    return out


def _poles_table(modes: list[dict], fv, zv, title: str, none: str, pairs: list[dict] | None = None) -> str:
    """The camera's own poles against the nearest accelerometer mode; one more than 1 % from every mode is said to
    be no mode of theirs, and named where it lies near a product of the strongest motion (`_products`)."""
    if not fv:
        return f"<p>{none}</p>"
    fa = np.array([m["freq_hz"] for m in modes], float)
    products = _products(modes, pairs or [])
    rows = []
    for i, f in enumerate(fv):
        f = float(f)
        near = int(np.argmin(np.abs(fa - f))) if len(fa) else None
        diff = (f - fa[near]) / fa[near] if near is not None else None
        note = ""
        if diff is None or abs(diff) > 0.01:
            note = "no accelerometer mode within 1 %"
            close = [(abs(f - fp) / fp, fp, name) for fp, name in products if fp > 0 and abs(f - fp) < 0.05 * fp]
            if close:
                _, fp, name = min(close)
                note += f"; near {name} ({fp:.1f} Hz), where the strongest motion's image is not quite linear"
        rows.append([str(i + 1), _num(f, ".2f"), _num(zv[i] if i < len(zv) else None, ".2f", 100),
                     _mode_name(modes, near) if near is not None else "&ndash;", _num(diff, "+.2f", 100), note])
    return (f"<p>{title}, against the nearest accelerometer mode:</p>"
            + _table(["#", "frequency (Hz)", "damping (%)", "nearest mode", "difference (%)", "note"], rows, 1))


def _sensor_table(sensors: list[str], header: str, values) -> str:
    """One value per sensor (named, or numbered where the document has fewer names)."""
    return _table(["sensor", header], [[escape(sensors[j] if j < len(sensors) else f"sensor {j + 1}"),
                                        _num(x, ".3f")] for j, x in enumerate(values)])


def _correlation(doc: dict) -> str:
    c = doc.get("correlation")
    out = []
    modes = doc["modes"]
    fitted = (doc.get("video") or {}).get("modes_fitted", [])
    if c:
        rows = []
        for p in c.get("pairs", []):
            a, b = p.get("a"), p.get("b")
            ma = fitted[a] if isinstance(a, int) and a < len(fitted) else a
            mb = fitted[b] if isinstance(b, int) and b < len(fitted) else b
            below = p.get("below_noise_floor") is True
            floor = (f'{_num(p.get("video_amplitude_um"), ".3g")} / {_num(p.get("noise_floor_um"), ".3g")}'
                     + (' <span class="bad">below the noise floor: not judged</span>' if below else ""))
            rows.append([_mode_name(modes, ma), _mode_name(modes, mb),
                         (f'<span class="bad">{_num(p.get("mac"), ".3f")}</span>' if below
                          else _num(p.get("mac"), ".3f")), _num(p.get("expected_mac"), ".3f"), floor,
                         _num(p.get("scale_factor_abs"), ".3g"), _num(p.get("scale_factor_phase_deg"), "+.1f"),
                         _num(p.get("freq_a_hz"), ".2f"), _num(p.get("freq_b_hz"), ".2f"),
                         _num(p.get("freq_diff_rel"), "+.2f", 100)])
        out.append("<h2>Correlation: accelerometers (a) vs video (b)</h2>")
        out.append(_verdict(c.get("verdict")))
        out.append(_table(["mode a", "mode b", "MAC", "MAC the noise allows",
                           "video amplitude / noise floor (&micro;m)", "|scale a/b|", "scale phase (deg)", "f a (Hz)",
                           "f b (Hz)", "&Delta;f (%)"], rows, 2)
                   if rows else "<p>No pairs.</p>")
        sensors = [str(s) for s in doc.get("sensors", [])]
        comac = c.get("comac", [])
        if comac:
            out.append("<h3>CoMAC per sensor</h3>")
            out.append(_sensor_table(sensors, "CoMAC", comac))
    ods = doc.get("ods", [])
    if ods:
        out.append("<h2>ODS: accelerometers vs video</h2>")
        out.append(_table(["line", "frequency (Hz)", "MAC"],
                          [[str(i + 1), _num(o.get("freq_hz"), ".2f"), _num(o.get("mac"), ".3f")]
                           for i, o in enumerate(ods) if isinstance(o, dict)]))
    return "".join(out)


def _inline(doc: dict, folder: Path, suffix: str):
    """(key, file, base64 data or None when missing) for each output file of the analysis ending in `suffix`."""
    for key, rel in doc["files"].items():
        if not (isinstance(rel, str) and rel.lower().endswith(suffix)):
            continue
        path = folder / rel
        if not path.is_file():
            log.warning("report: %s not found; left out", path)
            yield key, rel, None
            continue
        yield key, rel, base64.b64encode(path.read_bytes()).decode("ascii")


def _figures(doc: dict, folder: Path) -> str:
    out = []
    for key, rel, data in _inline(doc, folder, ".png"):
        if data is None:
            out.append(f'<p class="bad">{escape(rel)} not found.</p>')
            continue
        out.append(f'<figure><img src="data:image/png;base64,{data}" alt="{escape(str(key))}">'
                   f"<figcaption>{escape(str(key))} ({escape(rel)})</figcaption></figure>")
    return ("<h2>Figures</h2>" + "".join(out)) if out else ""


def _settings(doc: dict) -> str:
    s = doc.get("settings")
    if not s:
        return ""
    return f"<details><summary>Settings</summary><pre>{escape(json.dumps(s, indent=1))}</pre></details>"


def _summary(doc: dict, setup: dict) -> str:
    """The page's top: the setup, the modes with their MAC, the quality of the take, and a verdict line."""
    modes = doc["modes"]
    fitted = (doc.get("video") or {}).get("modes_fitted", [])
    c = doc.get("correlation") or {}
    by_mode = {}
    for p in c.get("pairs", []):
        b = p.get("b")
        k = fitted[b] if isinstance(b, int) and b < len(fitted) else None
        if k is not None:
            by_mode[int(k)] = p
    rows = []
    for k, m in enumerate(modes):
        p = by_mode.get(k)
        mac = "&ndash;" if p is None else (_num(p.get("mac"), ".3f")
                                           + (" (below the video's noise floor)" if p.get("below_noise_floor") else ""))
        scale = "&ndash;" if p is None else _num(p.get("scale_factor_abs"), ".2f")
        rows.append([str(k + 1), _num(m["freq_hz"], ".2f"), _num(m["damping"], ".2f", 100), mac, scale])
    verdict = (c.get("verdict") or {}).get("line")
    notes = doc.get("notes") or []
    if verdict:
        line = escape(str(verdict))
    elif doc.get("video"):
        line = "The video's shapes were fitted; no MAC verdict was made."
    else:
        line = (f"{len(modes)} modes from the accelerometers; no video side"
                + (f" ({len(notes)} note(s) below)" if notes else "") + ".")
    cls = "ok" if (c.get("verdict") or {}).get("status") == "met" else ("bad" if notes or verdict else "")
    band = doc.get("band_hz") or [None, None]
    setup_rows = [[escape(k), escape(str(v))] for k, v in setup.items()]
    setup_rows += [["hits averaged", f"{escape(str(doc.get('n_averages', '?')))} of {len(doc.get('takes', []))}"],
                   ["sensors", escape(", ".join(str(s) for s in doc.get("sensors", [])))],
                   ["fit band", f"{_num(band[0], '.0f')} to {_num(band[-1], '.0f')} Hz"]]
    return ("<h2>Summary</h2>" + f'<p class="{cls}"><b>Verdict:</b> {line}</p>'
            + _table(["", ""], setup_rows, 2)
            + (_table(["mode", "frequency (Hz)", "damping (%)", "MAC video/accelerometers", "|scale|"], rows)
               if doc.get("video") else _table(["mode", "frequency (Hz)", "damping (%)"], [r[:3] for r in rows])))


def _animations(doc: dict, folder: Path) -> str:
    """The modes in motion: each animation inline (a GIF in the page itself)."""
    out = []
    for key, _, data in _inline(doc, folder, ".gif"):
        if data is None:
            continue
        out.append(f'<figure style="display:inline-block"><img src="data:image/gif;base64,{data}" '
                   f'alt="{escape(str(key))}"><figcaption>mode {escape(str(key).rpartition("_")[2].lstrip("0"))}'
                   "</figcaption></figure>")
    return ("<h2>The modes in motion</h2><p>Each shape through one cycle (grey: at rest), exaggerated.</p>"
            + "".join(out)) if out else ""


RENDER_WIDTH_PX = 480     # the render's frames, downscaled, as one animated WebP in the page


def render_video(folder: Path) -> str:
    """The reconstruction's magnified novel-view render (`odsplat render`'s frames in `folder`) inline, as an
    animated WebP: browsers play it in the page, where they cannot play the mp4 this OpenCV build writes
    (MPEG-4 Part 2)."""
    frames = sorted(folder.glob("frame_*.png")) if folder.is_dir() else []
    if not frames:
        return ""
    from PIL import Image

    images = []
    for path in frames:
        with Image.open(path) as im:
            w, h = im.size
            scale = min(1.0, RENDER_WIDTH_PX / w)
            images.append(im.convert("RGB").resize((max(1, round(w * scale)), max(1, round(h * scale)))))
    buf = io.BytesIO()
    images[0].save(buf, format="WEBP", save_all=True, append_images=images[1:], duration=120, loop=0, quality=80)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return ("<h2>The magnified render</h2><p>The reconstruction seen from new viewpoints as time runs, magnified "
            f"in 3D (`odsplat render`, {len(frames)} frames; the mp4 lies beside them).</p>"
            f'<img src="data:image/webp;base64,{data}" alt="render">')


def capture_setup(capture: Capture) -> dict:
    """The setup in a few facts, from the capture and (where they ran) sync and poses: what the summary shows."""
    m = capture.manifest
    out = {"capture": capture.root.name}
    if m.daq_sample_rate_hz:
        out["DAQ"] = f"{m.daq_sample_rate_hz:g} Hz, {len(m.channels)} channels"
    if m.camera.fps:
        out["camera"] = f"{m.camera.fps:g} fps, {m.camera.width_px}x{m.camera.height_px} px, {m.camera.bit_depth} bit"
    try:
        from odsplat.sync import load_sync

        sync = load_sync(capture)
        res = [abs(t.residual_frames) for t in sync.ok if t.residual_frames is not None]
        out["views synced"] = (f"{len(sync.ok)} of {len(sync.takes)}"
                               + (f", timing residual median {np.median(res):.3f} frame" if res else ""))
    except InputError:
        pass
    try:
        from odsplat.reconstruction import PoseResult

        poses = PoseResult.read(capture)
        takes = [v for v in poses.views if v.kind == "take"]
        out["views posed"] = f"{len(takes)}"
        rms = [v.reproj_rms_px for v in takes if v.reproj_rms_px is not None]
        if rms:
            out["views posed"] += f", reprojection {float(np.median(rms)):.2f} px rms median ({poses.method})"
    except InputError:
        pass
    return out


def render_report(doc: dict, folder: Path, title: str, setup: dict | None = None, video: str = "") -> str:
    """The report's HTML from a loaded analysis.json (`folder` holds it and its plots); `setup`: facts of the
    capture for the summary (capture_setup); `video`: the render's section (render_video)."""
    sections = [_summary(doc, setup or {}), _notes(doc), _animations(doc, folder), video, _hits(doc), _modes(doc),
                _video(doc), _correlation(doc), _figures(doc, folder), _settings(doc)]
    return _PAGE.format(title=escape(str(doc.get("capture") or title)),
                        created=escape(str(doc.get("created_utc", "(no date)"))),
                        n_sensors=len(doc.get("sensors", [])), n_avg=escape(str(doc.get("n_averages", "?"))),
                        sections="\n".join(s for s in sections if s))


def write_report(capture: Capture) -> Path:
    """derived/analysis/report.html from derived/analysis/analysis.json and the plots it lists; returns its path."""
    doc = read_analysis(capture)
    path = capture.paths.report_html
    atomic_write_text(path, render_report(doc, capture.paths.analysis_dir, capture.root.name, capture_setup(capture),
                                          render_video(capture.paths.render_dir)))
    log.info("report written to %s", path)
    return path
