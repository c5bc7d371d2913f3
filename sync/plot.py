"""The sync plot, `derived/sync.png`: every take's hammer pulse locked to its onset, each take's frame
offset, and the residuals and cross-checks behind them."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from odsplat.spine.impulse import half_sine
from odsplat.spine.store import Capture

from .align import SyncResult, force_channel


def plot_sync(capture: Capture, result: SyncResult, path: Path | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = path or capture.paths.sync_png
    fig, (ax_f, ax_o, ax_r) = plt.subplots(3, 1, figsize=(9, 10), constrained_layout=True)
    fps = result.fps or 1.0
    ok = result.ok
    for t in ok:
        if t.hit_daq_time_s is None:  # on its own frame times: no pulse to show
            continue
        with capture.open_take(t.name) as r:
            f = r.channel(force_channel(r))
            tt = r.daq_t0_s + np.arange(len(f)) / r.sample_rate_hz - t.hit_daq_time_s
        near = (tt > -1e-3) & (tt < 4e-3)
        ax_f.plot(1e3 * tt[near], f[near], ".", ms=2)
    hits = [t for t in ok if t.hit_daq_time_s is not None]
    if hits:
        t = hits[0]
        s = np.linspace(-1e-3, 4e-3, 500)
        ax_f.plot(1e3 * s, half_sine(s, 0.0, t.peak_force_n, t.pulse_duration_s), "k-", lw=0.8,
                  label=f"half sine fitted to {t.name}")
        ax_f.legend(loc="upper right")
    ax_f.axvline(0.0, color="k", lw=0.5)
    ax_f.set(xlabel="time after the impact onset [ms]", ylabel="force [N]",
             title="hammer pulses, locked to their onsets")

    names = [t.name for t in result.takes]
    x = np.arange(len(names))
    for i, t in enumerate(result.takes):
        if t.status != "ok":
            ax_o.plot(i, 0, "rx")
            continue
        if t.method == "frames":  # on its own frame times
            ax_o.plot(i, t.offset_s * fps, "^", color="C2")
        elif t.method == "ttl":  # a line through many edges: far finer than one edge's residual
            ax_o.plot(i, t.offset_s * fps, "o", color="C0")
        else:
            ax_o.errorbar(i, t.offset_s * fps, yerr=t.residual_frames, fmt="s", color="C1")
    ax_o.set(ylabel="offset [frames]", title="middle of the trigger frame's exposure after the impact "
             "(o strobe, s images, ^ own frame times: no force, x excluded)")
    ax_o.set_xticks(x, names, rotation=90, fontsize=7)

    fs = capture.manifest.daq_sample_rate_hz or 1.0
    for label, attr, scale in (("image - strobe [frames]", "image_check_frames", 1.0),
                               ("response lag after locking [DAQ samples / 10]", "xcorr_lag_s", fs / 10)):
        ys = [np.nan if getattr(t, attr) is None else getattr(t, attr) * scale for t in result.takes]
        ax_r.plot(x, ys, "o-", ms=3, label=label)
    ax_r.axhline(0.0, color="k", lw=0.5)
    ax_r.set_xticks(x, names, rotation=90, fontsize=7)
    ax_r.legend()
    ax_r.set(title="cross-checks")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["plot_sync"]
