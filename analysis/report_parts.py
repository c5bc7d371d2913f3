"""The report's parts that read beyond analysis.json: the takes the analysis left out and why (the capture's own
records), each mode's interactive 3D shape (plots/shapes3d.json, drawn by plotly.js inlined from the plotly package),
the noise in plain words, and the figures' captions. Each returns plain text and numbers for the templates; nothing
read from a file reaches the page but numbers re-serialised here."""
from __future__ import annotations

import itertools
import json
import logging
import math
from importlib import resources
from pathlib import Path

from markupsafe import Markup

from odsplat.spine.errors import InputError, OdsplatError
from odsplat.spine.qcfile import QCFile
from odsplat.spine.store import Capture

from .document import AnalysisDocument, PairEntry
from .pagekit import finite, index_in, num, own_file, read_own
from .shape3d import parse_shapes

log = logging.getLogger(__name__)

# ---------------------------------------------------------------------------------------------- the takes


def _reason(flags: tuple[str, ...], notes: str) -> str:
    """A take's QC flags and notes as words: "tags not visible (1 floor AprilTag(s) visible, 2 needed)"."""
    words = ", ".join(f.replace("_", " ") for f in flags)
    if notes:       # the notes say it in full; the flags only where the notes do not name them
        said = all(f.replace("_", " ") in notes.lower() for f in flags)
        return notes if said or not words else f"{words} ({notes})"
    return words or "rejected (no reason recorded)"


def capture_takes(capture: Capture) -> dict[str, dict]:
    """Every take of the capture by name: {"view", "qc", "why"}: its QC verdict as it stands (recorded with the take,
    or the qc stage's for one recorded unchecked) and, where it was rejected, why in words."""
    try:
        checked = {t.name: t for t in QCFile.read(capture.paths.qc_json, capture.id).takes}
    except InputError:
        checked = {}
    out = {}
    for t in capture.manifest.takes:
        row = {"view": t.view, "qc": t.qc, "why": ""}
        qc = checked.get(t.name)
        if t.qc == "unchecked" and qc is not None:
            row["qc"] = qc.checked
            row["why"] = "; ".join(qc.details or qc.reasons)
        if t.status not in ("complete", "recovered"):
            row.update(qc="rejected", why=f"take {t.status}")
        elif row["qc"] == "rejected" and not row["why"]:
            try:
                with capture.open_take(t.name) as reader:
                    info = reader.qc
                row["why"] = _reason(info.flags, info.notes)
            except (OdsplatError, OSError, KeyError) as e:
                row["why"] = f"rejected (its QC record could not be read: {e})"
        out[t.name] = row
    return out


def takes_part(doc: AnalysisDocument, takes: dict[str, dict] | None) -> dict:
    """The first screen's takes: one line (how many used, of how many recorded) and a row per take left out, with
    why and the take of its view that redid it. `takes`: the capture's (capture_takes), or None (the document
    alone: the analysis's own rejected hits)."""
    rejected = {h.take: "; ".join(h.reasons) or "rejected" for h in doc.rejected_hits}
    used = [t for t in doc.takes if t not in rejected]
    takes = takes or {}
    left = []           # (name, view, why, the used take of its view that came after it)
    for name, t in takes.items():
        if name in doc.takes or t["qc"] == "accepted":
            continue
        later = [n for n, u in takes.items() if u["view"] == t["view"] and n > name and n in used]
        left.append((name, t["view"], t["why"] or f"QC {t['qc']}", later[0] if later else None))
    left += [(name, takes.get(name, {}).get("view"), f"hit rejected by the analysis: {why}", None)
             for name, why in rejected.items()]
    rows = []
    for (view, why, redone), group in itertools.groupby(left, key=lambda r: r[1:]):   # one row per run alike
        names = [g[0] for g in group]
        has_view = view is not None and takes
        rows.append({"take": names[0] if len(names) == 1 else f"{names[0]} to {names[-1]} ({len(names)} takes)",
                     "view": "-" if view is None else str(view), "css": "warn", "why": why, "redone": redone,
                     "missing": bool(has_view and redone is None and not any(
                         takes[n]["view"] == view for n in used if n in takes))})
    n_all = len(takes) if takes else len(doc.takes)
    line = f"{len(used)} of {n_all} recorded takes used"
    n_left = len(left)
    redone = sum(1 for r in left if r[3] is not None)
    if left:
        line += f"; {n_left} left out" + (f", {redone} of them redone" if redone else "") + ":"
    else:
        line += "; none left out."
    return {"line": line, "rows": rows}


# ---------------------------------------------------------------------------------------------- the 3D shapes

def _read_shapes(doc: AnalysisDocument, folder: Path) -> dict:
    """plots/shapes3d.json, the analysis's own file, read and checked (`shape3d.parse_shapes`). ValueError naming
    what is wrong."""
    path = own_file(folder, doc.files.get("shapes3d"))
    if isinstance(path, str):
        raise ValueError(path)
    return parse_shapes(read_own(path))


def _plotly_js() -> Markup:
    """plotly.js as the plotly package ships it (minified; no "</script" in it, checked)."""
    text = (resources.files("plotly") / "package_data" / "plotly.min.js").read_text(encoding="utf-8")
    if "</script" in text.lower():
        raise OdsplatError("plotly.min.js holds '</script' and cannot be inlined")
    return Markup(text)


def _script() -> Markup:
    return Markup(Path(__file__).with_name("templates").joinpath("shapes3d.js").read_text(encoding="utf-8"))


def shapes_part(doc: AnalysisDocument, folder: Path) -> dict:
    """Each mode's section: its header and status, the 3D shape where plots/shapes3d.json has it (the data
    re-serialised here as JSON for the page's script, "<" escaped), grey with why where the verdict did not judge it
    (`AnalysisDocument.not_judged`)."""
    out = {"data": None, "plotly": None, "script": None, "problem": None, "surface": "", "modes": [],
           "why": "the analysis wrote no 3D shapes (no video surface and no placed sensors, or no plots)"}
    shapes = None
    if doc.files.get("shapes3d"):
        try:
            shapes = _read_shapes(doc, folder)
        except (ValueError, OSError) as e:
            out["problem"] = f"{doc.files['shapes3d']}: {e}; the 3D shapes are left out"
            log.warning("report: %s", out["problem"])
    grey = doc.not_judged()
    verdict = doc.correlation.verdict if doc.correlation is not None else None
    status = {st.mode: st.status for st in verdict.modes} if verdict is not None else {}
    page_modes = []
    for k, m in enumerate(doc.modes):
        s = shapes["modes"].get(k + 1) if shapes is not None else None
        why = grey.get(k)
        row = {"mode": str(k + 1), "freq": num(m.freq_hz, ".2f"), "damping": num(m.damping, ".2f", 100),
               "status": why or status.get(k + 1, ""), "judged": why is None and (s is None or s["judged"]),
               "shape": s is not None, "index": len(page_modes), "clip": None}
        if s is not None:
            page_modes.append({"judged": row["judged"], "re": s["re"].tolist(), "im": s["im"].tolist()})
        out["modes"].append(row)
    if shapes is not None and page_modes:
        data = {"points_m": shapes["points"].tolist(), "faces": shapes["faces"].tolist(),
                "lines": shapes["lines"].tolist(), "modes": page_modes}
        out["data"] = Markup(json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c"))
        out["plotly"], out["script"] = _plotly_js(), _script()
        out["surface"] = (f"surface ({len(shapes['points'])} points, {len(shapes['faces'])} triangles)"
                          if len(shapes["faces"]) else f"sensors ({len(shapes['points'])} points)")
    return out


# ---------------------------------------------------------------------------------------------- the noise

BAR_EM_PER_DECADE = 6.0      # the noise section's bars: amplitude over floor on a log scale, from 0.1
BAR_MAX_EM = 24.0


def noise_part(doc: AnalysisDocument, pairs: tuple[PairEntry, ...], mode_name) -> dict | None:
    """One row per video mode: its amplitude against the floor it needs to be judged, as numbers, a bar on a log
    scale and words; the section's one paragraph. None without a video noise floor."""
    v = doc.video
    nf = v.noise_floor if v is not None else None
    if nf is None or not pairs:
        return None
    rows = []
    for p in pairs:
        a, f = finite(p.video_amplitude_um), finite(p.noise_floor_um)
        ratio = a / f if a is not None and f else None
        below = bool(p.below_noise_floor)
        width = 0.0 if ratio is None or ratio <= 0 else BAR_EM_PER_DECADE * (math.log10(ratio) + 1)
        width = min(max(width, 0.2), BAR_MAX_EM)
        rows.append({"mode": mode_name(p), "amplitude": num(a, ".3g"), "floor": num(f, ".3g"),
                     "ratio": num(ratio, ".2g"), "grey": below, "width": f"{width:.2f}",
                     "floor_at": f"{BAR_EM_PER_DECADE - width:.2f}",
                     "words": ("below its floor: not judged" if below else
                               f"{num(ratio, '.2g')} times its floor" if ratio is not None else "")})
    text = (f"Where nothing moves, the video's surface points still wander by {num(nf.sigma_um, '.3g')} µm "
            f"(rms, per point and timestep): that is its noise. A mode's shape is judged only where the mode moves "
            f"the structure well above it: its amplitude at the sensors at least {num(nf.floor_sigmas, '.3g')} "
            f"times the noise there (its floor). Below the floor a shape is drawn grey and not judged.")
    return {"text": text, "rows": rows,
            "scale": f"Bars: amplitude over floor on a log scale ({BAR_EM_PER_DECADE:g} em a decade, from 0.1); "
                     "the red mark is the floor."}


# ---------------------------------------------------------------------------------------------- captions

_CAPTIONS = {
    "frf": "Frequency response functions, each accelerometer over the hammer, averaged over the hits: magnitude "
           "(dashed: the fitted model), phase and coherence.",
    "stabilisation": "Stabilisation chart: the poles at each model order; the selected modes dotted.",
    "automac": "AutoMAC of the accelerometers' mode shapes: where two modes read high, the sensors cannot tell "
               "them apart.",
    "mac": "MAC of the video's shapes against the accelerometers' at the sensors (outlined: the pairs).",
    "time": "The video's motion at the sensors against the accelerometers', in time.",
}


def caption(doc: AnalysisDocument, key: str) -> str:
    """A figure's caption in words, from its key in analysis.json's files: an ODS line's with its frequency and
    MAC, the others by kind."""
    if key in _CAPTIONS:
        return _CAPTIONS[key]
    if key.startswith("ods_"):
        i = index_in(int(key[4:]) - 1, len(doc.ods)) if key[4:].isdigit() else None
        if i is not None:
            return (f"Operational deflection shape at {num(doc.ods[i].freq_hz, '.2f')} Hz: the video's against the "
                    f"accelerometers' (MAC {num(doc.ods[i].mac, '.3f')}).")
        return (f"Operational deflection shape at spectral line {key[4:].lstrip('0') or '0'}: the video and the "
                "accelerometers.")
    return key.replace("_", " ")


__all__ = ["caption", "capture_takes", "noise_part", "shapes_part", "takes_part"]
