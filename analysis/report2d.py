"""The 2D path's report, derived/analysis/report.html for a capture without force: its setup, the mode table (modes
below the floor in grey, saying so), the spectrum, each mode's shape on the frame and amplified clip, the
stabilisation chart. Figures and clips are inlined (data: URIs), so the page stands alone."""
from __future__ import annotations

import base64
from pathlib import Path

import jinja2

from odsplat.spine.store import Capture

from .clips import BAND
from .video2d import read_video2d

_TEMPLATES = jinja2.Environment(loader=jinja2.FileSystemLoader(Path(__file__).with_name("templates")),
                                autoescape=True)
MEDIA = {".png": "image/png", ".mp4": "video/mp4"}


def _uri(folder: Path, rel: str | None) -> str | None:
    """A file of the analysis (a path it wrote, inside its folder) as a data: URI; None where there is none."""
    if not rel:
        return None
    path = (folder / rel).resolve()
    if folder.resolve() not in path.parents or path.is_symlink() or not path.is_file():
        return None
    return f"data:{MEDIA[path.suffix]};base64,{base64.b64encode(path.read_bytes()).decode('ascii')}"


def _rows(doc: dict, folder: Path) -> list[dict]:
    files = doc.get("files", {})
    rows = []
    for k, m in enumerate(doc["modes"], 1):
        amp = f"{m['amplitude_px']:.3g} px"
        if m.get("amplitude_m") is not None:
            amp += f" ({1e6 * m['amplitude_m']:.3g} µm)"
        z = f"{100 * m['damping']:.2f}" if m.get("damping") is not None else "FDD peak, no pole: an ODS"
        rows.append(dict(k=k, f=f"{m['freq_hz']:.3f}", z=z, mpc=f"{m['mpc']:.2f}", amp=amp,
                         floor=f"{m['floor_mac']:.3f}", above=m["above_floor"],
                         state="above the floor" if m["above_floor"] else "below the floor: shape not judged",
                         shape=_uri(folder, files.get(f"shape_{k:02d}")), clip=_uri(folder, m.get("clip")),
                         band=f"{m['freq_hz'] * (1 - BAND):.4g}-{m['freq_hz'] * (1 + BAND):.4g}",
                         alpha=f"{m['clip_alpha']:.0f}" if m.get("clip_alpha") else "",
                         title="Mode" if m.get("kind", "mode") == "mode" else "FDD peak",
                         slow=(f"{doc['fps'] / 30.0:.3g}x slower than filmed" if doc["fps"] > 30.5 else
                               "the speed filmed" if doc["fps"] > 29.5 else
                               f"{30.0 / doc['fps']:.3g}x faster than filmed")))
    return rows


def render_video2d_report(capture: Capture) -> str:
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
    return _TEMPLATES.get_template("video2d.html").render(
        title=doc["capture"], created=doc.get("created_utc", ""), setup=setup, modes=_rows(doc, folder),
        floor_mac=doc["floor_mac"], notes=doc.get("notes", []), spectrum=_uri(folder, files.get("spectrum")),
        stabilisation=_uri(folder, files.get("stabilisation")))


__all__ = ["render_video2d_report"]
