"""Figures of an analysis (FRFs, stabilisation chart, MAC, 3D ODS, video motion) as matplotlib Figures, and their
PNGs. Figures are built with the object API (no pyplot), so they hold no global state and a GUI can embed them."""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from odsplat.spine.atomic import atomic_open
from odsplat.spine.errors import InputError

from .animate import ods_gif
from .correlation import mac
from .shape3d import write_shapes

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from .correlation import Correlation
    from .ema import ModalFit, StabilisationChart
    from .frf import FRFResult
    from .result import AnalysisResult

log = logging.getLogger(__name__)

DPI = 110
MAX_SCATTER_POINTS = 3000
ODS_SCALE = 0.10                      # the largest drawn displacement, as a share of the structure's size
_STATUS_STYLE = {                     # stabilisation chart: (marker, colour, label), drawn in this order
    "new": ("+", "0.6", "new"),
    "freq": ("x", "tab:orange", "stable frequency"),
    "damping": ("d", "tab:blue", "stable frequency + damping"),
    "stable": ("o", "tab:green", "stable"),
}


def _figure(w_in: float, h_in: float) -> Figure:
    # matplotlib is imported when a figure is drawn: the viewer and the command line import the analysis without
    # drawing (a third of a second)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in), dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _sensor_labels(sensors, apart_m: float) -> list[tuple[np.ndarray, str]]:
    """One label per place: the sensors within apart_m of each other (a triaxial block's channels) named together,
    so that their names do not print over one another."""
    out: list[tuple[np.ndarray, list[str]]] = []
    for s in sensors:
        if s.position_m is None:
            continue
        p = np.asarray(s.position_m, float)
        near = next((item for item in out if np.linalg.norm(item[0] - p) <= apart_m), None)
        if near is None:
            out.append((p, [s.name]))
        else:
            near[1].append(s.name)
    return [(p, ", ".join(names)) for p, names in out]


def _rectangle(*args, **kwargs):
    from matplotlib.patches import Rectangle

    return Rectangle(*args, **kwargs)


def _positive(a: np.ndarray) -> np.ndarray:
    """|a| with zeros and non-finite values as NaN, so log axes skip them."""
    m = np.abs(np.asarray(a))
    return np.where(np.isfinite(m) & (m > 0), m, np.nan)


def _log_if_data(ax, y: np.ndarray) -> None:
    ax.set_yscale("log" if np.isfinite(y).any() else "linear")


def _mode_lines(axes, freqs_hz) -> None:
    for f in np.asarray(freqs_hz, float).ravel():
        if np.isfinite(f):
            for ax in axes:
                ax.axvline(f, color="0.5", lw=0.7, ls=":", zorder=0)


# ------------------------------------------------------------------------------------------------ FRF

def plot_frf(frf: FRFResult, modes: ModalFit | None = None) -> Figure:
    """|H1| (log) per output with the LSFD synthesis dashed over the fitted band, phase, and coherence."""
    fig = _figure(10, 8)
    ax_m, ax_p, ax_c = fig.subplots(3, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1.5, 1]})
    f = np.asarray(frf.freq_hz, float)
    h = np.asarray(frf.h1).reshape(len(f), -1)
    coh = np.asarray(frf.coherence, float).reshape(len(f), -1)
    names = list(frf.output_names) or [f"output {j + 1}" for j in range(h.shape[1])]
    synth, band = None, None
    if modes is not None:
        band = modes.lsfd.band_hz
        fb = f[(f >= band[0]) & (f <= band[1]) & (f > 0)]
        try:
            synth = (fb, np.asarray(modes.lsfd.synthesize(fb)).reshape(len(fb), -1))
        except Exception as exc:  # a plot must not fail an analysis
            log.warning("plot_frf: no LSFD synthesis: %s", exc)
    mag = _positive(h)
    for j in range(h.shape[1]):
        (line,) = ax_m.plot(f, mag[:, j], lw=1.0, label=names[j] if j < len(names) else f"output {j + 1}")
        c = line.get_color()
        ax_p.plot(f, np.degrees(np.angle(h[:, j])), lw=0.8, color=c)
        ax_c.plot(f, coh[:, j], lw=0.8, color=c)
        if synth is not None and j < synth[1].shape[1]:
            ax_m.plot(synth[0], _positive(synth[1][:, j]), ls="--", lw=1.0, color=c, alpha=0.9)
    _log_if_data(ax_m, mag)
    if synth is not None:
        ax_m.plot([], [], "k--", lw=1.0, label=f"LSFD fit {band[0]:.0f}-{band[1]:.0f} Hz")
    if modes is not None:
        _mode_lines((ax_m, ax_p, ax_c), modes.freq_hz)
    ax_m.set(ylabel=f"|H1| ({frf.output_unit}/{frf.input_unit})",
             title=f"H1 from '{frf.input_name}', {frf.n_averages} averages")
    ax_m.legend(fontsize="small", ncols=2 if h.shape[1] > 4 else 1)
    ax_p.set(ylabel="phase (deg)", ylim=(-180, 180), yticks=[-180, -90, 0, 90, 180])
    ax_c.set(ylabel="coherence", ylim=(0, 1.05), xlabel="frequency (Hz)")
    if band is not None:       # the analysis band, where the modes are: not the DAQ's whole Nyquist range
        ax_c.set_xlim(0.0, min(float(np.nanmax(f)), 1.1 * float(band[1])))
        inside = (f >= band[0]) & (f <= 1.1 * band[1]) & np.isfinite(mag).all(axis=1)
        if inside.any() and np.nanmax(mag[inside]) > 0:
            lo_y = np.nanmin(mag[inside][mag[inside] > 0]) if (mag[inside] > 0).any() else None
            ax_m.set_ylim(0.5 * lo_y if lo_y else None, 2 * float(np.nanmax(mag[inside])))
    elif len(f) and np.isfinite(f).any():
        ax_c.set_xlim(np.nanmin(f), np.nanmax(f))
    for ax in (ax_m, ax_p, ax_c):
        ax.grid(True, alpha=0.3)
    return fig


def plot_stabilisation(chart: StabilisationChart, frf: FRFResult | None = None, *,
                       band_hz: tuple[float, float] | None = None, selected_hz: Sequence[float] = ()) -> Figure:
    """Model order against pole frequency, one marker per status, over the sum of |H1| (log, right axis)."""
    fig = _figure(10, 6)
    ax = fig.subplots()
    order, poles, status = chart.flat()
    freq = np.abs(poles) / (2 * np.pi)
    lo, hi = band_hz if band_hz is not None else (None, None)
    if frf is not None:
        f = np.asarray(frf.freq_hz, float)
        keep = np.ones(len(f), bool) if band_hz is None else (f >= lo) & (f <= hi)
        total = np.nansum(np.abs(np.asarray(frf.h1).reshape(len(f), -1)), axis=1)[keep]
        twin = ax.twinx()
        twin.plot(f[keep], _positive(total), color="0.75", lw=1.0)
        _log_if_data(twin, _positive(total))
        twin.set_ylabel(f"sum of |H1| ({frf.output_unit}/{frf.input_unit})", color="0.5")
        ax.set_zorder(twin.get_zorder() + 1)   # the markers over the FRF
        ax.patch.set_visible(False)
    picked = np.zeros(len(freq), bool)      # a stable pole within 0.5 % of a selected one: the column it came from
    for f0 in selected_hz:
        picked |= np.abs(freq - f0) <= 0.005 * f0
    for key, (marker, colour, label) in _STATUS_STYLE.items():
        sel = status == key
        if band_hz is not None:
            sel &= (freq >= lo) & (freq <= hi)
        if key == "stable":
            sel &= ~picked
        if not sel.any():           # no legend entry for what the chart does not show
            continue
        small = key != "stable" or len(selected_hz)     # beside the selected columns the rest recede
        ax.scatter(freq[sel], order[sel], marker=marker, s=10 if small else 18, color=colour,
                   alpha=0.45 if small else 1.0, label=f"{label} ({int(sel.sum())})",
                   linewidths=0.8 if marker in "+x" else 0.3, edgecolors=None if marker in "+x" else "k")
    sel = picked & (status == "stable")
    if sel.any():
        ax.scatter(freq[sel], order[sel], marker="o", s=22, color="tab:red", edgecolors="k", linewidths=0.5,
                   label=f"stable, in a selected mode's column ({int(sel.sum())})")
    _mode_lines((ax,), selected_hz)
    if band_hz is not None:
        ax.set_xlim(lo, hi)
    ax.set(xlabel="frequency (Hz)", ylabel="model order",
           title="Stabilisation chart" + (f" ({len(selected_hz)} selected modes dotted)" if len(selected_hz) else ""))
    handles, labels = ax.get_legend_handles_labels()
    if handles:                     # below the axes: it never covers the poles
        fig.legend(handles, labels, loc="outside lower center", ncol=min(3, len(handles)), fontsize="small",
                   frameon=False)
    ax.grid(True, alpha=0.3)
    return fig


def plot_mac(correlation_or_mac_matrix: Correlation | np.ndarray, labels_a: Sequence[str] | None = None,
             labels_b: Sequence[str] | None = None, *, title: str = "MAC") -> Figure:
    """The MAC matrix (rows: set a, columns: set b) as an image with its values in the cells; the pairs of a
    Correlation are outlined."""
    corr = correlation_or_mac_matrix
    m = np.atleast_2d(np.asarray(getattr(corr, "mac", corr), float))
    if m.ndim != 2:
        raise InputError("plot_mac: mac", f"expected a 2-D MAC matrix; got shape {m.shape}")
    na, nb = m.shape
    la = list(labels_a) if labels_a is not None else [str(i + 1) for i in range(na)]
    lb = list(labels_b) if labels_b is not None else [str(j + 1) for j in range(nb)]
    fig = _figure(max(4.0, 1.3 + 0.75 * nb), max(3.5, 1.3 + 0.6 * na))
    ax = fig.subplots()
    im = ax.imshow(m, vmin=0, vmax=1, cmap="viridis", aspect="auto")
    for i in range(na):
        for j in range(nb):
            v = m[i, j]
            ax.text(j, i, "-" if not np.isfinite(v) else f"{v:.2f}", ha="center", va="center", fontsize=9,
                    color="k" if np.isfinite(v) and v > 0.6 else "w")
    for i, j in getattr(corr, "pairs", ()):
        ax.add_patch(_rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, ec="r", lw=1.5))
    ax.set_xticks(range(nb), lb[:nb], rotation=45 if nb > 4 else 0, ha="right" if nb > 4 else "center")
    ax.set_yticks(range(na), la[:na])
    ax.set_title(title)
    fig.colorbar(im, ax=ax, shrink=0.85)
    return fig


# ------------------------------------------------------------------------------------------------ ODS

def _rotation(shape: np.ndarray) -> complex:
    """exp(-i theta) that turns a complex shape closest to real (theta: half the angle of sum psi^2)."""
    s = np.nansum(np.asarray(shape, complex) ** 2)
    return complex(np.exp(-0.5j * np.angle(s))) if s != 0 else 1.0


def _video_ods(result: AnalysisResult, line_index: int, sub: np.ndarray) -> np.ndarray | None:
    if result.video is None or len(result.ods_surface) == 0 or len(sub) == 0:
        return None
    return result.ods_surface[line_index][sub]     # (n, 3) m/N


def plot_ods(result: AnalysisResult, line_index: int) -> Figure:
    """The ODS of line `line_index` in 3D: the video's surface points at rest (grey) and displaced (coloured by
    |ODS|), and the sensors with the accelerometer ODS (and the video's at the sensors) as arrows. Shapes are
    rotated by one phase (the accelerometer ODS's) to be closest to real, then their real part is drawn."""
    n_lines = len(result.ods_freq_hz)
    if not -n_lines <= line_index < n_lines:
        raise InputError("plot_ods: line_index", f"expected an index into {n_lines} ODS lines; got {line_index}")
    freq = float(result.ods_freq_hz[line_index])
    acc = np.asarray(result.ods_accel[line_index], complex) if result.ods_accel.size else None
    vid = np.asarray(result.ods_video[line_index], complex) if result.ods_video.size else None
    pos = np.stack([s.position_m for s in result.sensors]).astype(float)
    dirs = np.stack([s.direction for s in result.sensors]).astype(float)
    v = result.video
    pts = np.asarray(v.surface_points_m, float) if v is not None else np.zeros((0, 3))
    sub = np.linspace(0, len(pts) - 1, min(len(pts), MAX_SCATTER_POINTS)).round().astype(int)
    surf = _video_ods(result, line_index, sub)
    rot = _rotation(acc if acc is not None else surf if surf is not None else 0.0)
    every = np.concatenate([pts[sub], pos])
    every = every[np.isfinite(every).all(axis=1)]
    size = float(np.linalg.norm(np.ptp(every, axis=0))) if len(every) > 1 else 0.0
    size = size if size > 0 else 1.0
    disp = (surf * rot).real if surf is not None else None
    peak = np.nanmax(np.linalg.norm(disp, axis=1)) if disp is not None and len(disp) else np.nan
    if acc is not None and not (np.isfinite(peak) and peak > 0):
        peak = np.nanmax(np.abs((acc * rot).real)) if np.isfinite(acc).any() else np.nan
    scale = ODS_SCALE * size / peak if np.isfinite(peak) and peak > 0 else 0.0

    fig = _figure(9, 7.5)
    ax = fig.add_subplot(projection="3d")
    ax.computed_zorder = False            # the sensors and their arrows stay over the surface cloud
    if disp is not None:
        p = pts[sub]
        ax.scatter(*p.T, s=2, color="0.7", alpha=0.4, label="at rest")
        sc = ax.scatter(*(p + scale * disp).T, s=4, c=np.linalg.norm(np.abs(surf), axis=1), cmap="plasma",
                        label="video ODS")
        fig.colorbar(sc, ax=ax, shrink=0.6, pad=0.08, label="|ODS| (m/N)")
    elif len(sub):
        ax.scatter(*pts[sub].T, s=2, color="0.7", alpha=0.4, label="surface (no video shape)")
    ax.scatter(*pos.T, s=25, color="k", marker="s", label="sensors", zorder=4)
    arrows = [(acc, "tab:red", "accelerometer ODS"), (vid, "tab:blue", "video ODS at the sensors")]
    for shape, colour, label in arrows:
        if shape is not None and len(shape) == len(pos):
            vec = dirs * (scale * (shape * rot).real)[:, None]
            vec = np.where(np.isfinite(vec), vec, 0.0)
            ax.quiver(*pos.T, *vec.T, color=colour, lw=2, arrow_length_ratio=0.2, label=label, zorder=5)
    for where, names in _sensor_labels(result.sensors, 0.01 * size):
        ax.text(*where, f" {names}", fontsize=7, zorder=6)
    centre = np.mean([every.min(axis=0), every.max(axis=0)], axis=0) if len(every) else np.zeros(3)
    half = 0.5 * size * (1 + 2 * ODS_SCALE) if len(every) > 1 else 0.5
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - half, c + half)
    ax.set_box_aspect((1, 1, 1))
    ax.set(xlabel="x (m)", ylabel="y (m)", zlabel="z (m)")
    ax.set_title(f"ODS at {freq:.2f} Hz: real part x {scale:.3g} (largest = {100 * ODS_SCALE:.0f} % of the "
                 f"structure's {size:.2f} m)", fontsize=10)
    ax.legend(loc="upper left", fontsize="small")
    return fig


def plot_time(result: AnalysisResult) -> Figure:
    """The video's displacement at each sensor, along the sensor's direction, in micrometres."""
    fig = _figure(10, 4.5)
    ax = fig.subplots()
    v = result.video
    if v is None:
        ax.text(0.5, 0.5, "no video side", ha="center", va="center", transform=ax.transAxes)
        return fig
    x = np.asarray(v.sensor_displacement_m, float).reshape(len(v.times_s), -1)
    for j in range(x.shape[1]):
        name = result.sensors[j].name if j < len(result.sensors) else f"sensor {j + 1}"
        ax.plot(np.asarray(v.times_s) * 1e3, x[:, j] * 1e6, lw=1.0, label=name)
    ax.set(xlabel="time (ms)", ylabel="displacement (µm)", title="Video motion at the sensors, along their directions")
    ax.legend(fontsize="small")
    ax.grid(True, alpha=0.3)
    return fig


# ------------------------------------------------------------------------------------------------ files

def _mode_labels(freq_hz) -> list[str]:
    return [f"{k + 1}: {f:.1f} Hz" for k, f in enumerate(np.asarray(freq_hz, float))]


def write_plots(dest: Path, result: AnalysisResult) -> dict[str, str]:
    """Every figure of `result` as dest/plots/*.png; returns {key: path relative to dest}. A figure that fails is
    logged and left out: the plots must not cost the analysis they illustrate."""
    out = Path(dest) / "plots"
    out.mkdir(parents=True, exist_ok=True)
    m = result.modes
    jobs = {"frf": lambda: plot_frf(result.frf, m),
            "stabilisation": lambda: plot_stabilisation(m.chart, result.frf, band_hz=m.band_hz,
                                                         selected_hz=m.freq_hz)}
    if m.n_modes > 1 and len(result.sensors) > 1:      # over one sensor every pair of shapes reads 1
        labels, shapes = _mode_labels(m.freq_hz), np.nan_to_num(np.asarray(m.shapes, complex))
        jobs["automac"] = lambda: plot_mac(mac(shapes, shapes), labels, labels, title="AutoMAC, accelerometers")
    if result.correlation is not None and result.video is not None:
        idx = np.asarray(result.video.mode_index, int)
        la = [f"acc {s}" for s in _mode_labels(m.freq_hz)]
        jobs["mac"] = lambda: plot_mac(result.correlation, [la[i] for i in idx],
                                       [f"video {i + 1}" for i in idx], title="MAC: accelerometers vs video")
    if result.video is not None:
        jobs["time"] = lambda: plot_time(result)
    if result.video is not None or all(s.placed for s in result.sensors):   # a shape needs somewhere to be drawn
        for li in range(len(result.ods_freq_hz)):
            jobs[f"ods_{li + 1:02d}"] = lambda li=li: plot_ods(result, li)
    files = {}
    for key, make in jobs.items():
        path = out / f"{key}.png"
        try:
            fig = make()
            with atomic_open(path, "wb") as fh:
                fig.savefig(fh, format="png", dpi=DPI)
        except Exception as exc:  # noqa: BLE001 (see the docstring)
            log.warning("plot %s failed: %s", key, exc, exc_info=True)
            continue
        files[key] = f"plots/{path.name}"
    for key, (points, shape, title) in _animations(result).items():
        path = out / f"{key}.gif"
        try:
            data = ods_gif(points, shape, title=title)
            with atomic_open(path, "wb") as fh:
                fh.write(data)
        except Exception as exc:  # noqa: BLE001 (see the docstring)
            log.warning("animation %s failed: %s", key, exc, exc_info=True)
            continue
        files[key] = f"plots/{path.name}"
    try:
        if write_shapes(out / "shapes3d.json", result):
            files["shapes3d"] = "plots/shapes3d.json"
    except Exception as exc:  # noqa: BLE001 (see the docstring)
        log.warning("3D shapes failed: %s", exc, exc_info=True)
    return files


def _animations(result: AnalysisResult) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """Per mode, what to animate: the video's shape on the structure's surface where the video has the mode,
    else the accelerometers' shape at their positions (when every sensor is placed)."""
    m, v = result.modes, result.video
    out = {}
    video_rows = {int(k): r for r, k in enumerate(v.mode_index)} if v is not None else {}
    placed = all(sn.placed for sn in result.sensors) and result.sensors
    for k in range(m.n_modes):
        title = f"mode {k + 1}: {m.freq_hz[k]:.2f} Hz, {100 * m.damping[k]:.2f} %"
        if k in video_rows and len(v.surface_points_m):
            out[f"anim_{k + 1:02d}"] = (v.surface_points_m, v.surface_residues[video_rows[k]], title + " (video)")
        elif placed:
            pos = np.stack([sn.position_m for sn in result.sensors])
            dirs = np.stack([sn.direction for sn in result.sensors])
            out[f"anim_{k + 1:02d}"] = (pos, m.shapes[k][:, None] * dirs, title + " (accelerometers)")
    return out
