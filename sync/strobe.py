"""Frame times in DAQ time from the camera's exposure strobe (TTL) recorded on a DAQ channel.

Every exposure raises the strobe, dropped frames included, so the rising edges are the exposure
starts on the DAQ's clock. A straight line through edge time against pulse number gives the camera's
true frame period (its rate error against the DAQ) and, averaged over many edges, each exposure start
to a small fraction of a DAQ sample even though each edge is only known to within one sample.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from odsplat.spine.errors import InputError


@dataclass(frozen=True)
class StrobeTiming:
    """The strobe's pulse train, fitted. Times are DAQ times (s); `frame0_start_s` is counter 0's exposure start."""

    frame0_start_s: float
    period_s: float
    exposure_s: float
    n_pulses: int
    residual_frames: float          # rms misfit of the edges to the straight line, in frame periods
    anchor: str                     # how counter 0 was found: "end" (the strobe stops after the last frame)
                                    # or "trigger"
    flags: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    def start_s(self, counters: np.ndarray) -> np.ndarray:
        return self.frame0_start_s + np.asarray(counters, float) * self.period_s


def strobe_edges(volts: np.ndarray, *, level_v: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Rising and falling edges as fractional sample indices (linear interpolation through `level_v`).

    The default level is halfway between the low and high states. Edges touching lost (NaN) samples are
    left out: their time is unknown."""
    v = np.asarray(volts, float)
    finite = np.isfinite(v)
    if finite.sum() < 2:
        return np.empty(0), np.empty(0)
    if level_v is None:
        lo, hi = np.percentile(v[finite], [1, 99])
        if hi - lo <= 0:
            return np.empty(0), np.empty(0)
        level_v = 0.5 * (lo + hi)
    above = v >= level_v
    ok = finite[:-1] & finite[1:]
    rise = np.flatnonzero(~above[:-1] & above[1:] & ok)
    fall = np.flatnonzero(above[:-1] & ~above[1:] & ok)

    def frac(i: np.ndarray) -> np.ndarray:
        a, b = v[i], v[i + 1]
        return i + (level_v - a) / (b - a)

    return frac(rise), frac(fall)


def fit_strobe(volts: np.ndarray, sample_rate_hz: float, t0_s: float, counters: Sequence[int], *,
               nominal_fps: float, trigger_time_s: float | None, trigger_delay_s: float = 0.0,
               source: str = "ttl") -> StrobeTiming:
    """Fit the pulse train and find which pulse is counter 0.

    Counter 0 is found two ways. When the strobe stops well inside the record, its last pulse is the last
    frame of the recording (the highest counter stored). The first exposure starting at or after the
    camera's trigger (the DAQ trigger time plus `trigger_delay_s`) is counter 0 as well. With both, a
    disagreement is flagged; the end anchor counts pulses and is used.
    """
    counters = np.asarray(counters, int)
    if counters.size == 0:
        raise InputError(source, "the take holds no frames to time")
    rise, fall = strobe_edges(volts)
    if rise.size < 3:
        raise InputError(source, f"the exposure strobe shows {rise.size} rising edges; at least 3 are needed "
                                 "(is the camera's strobe output wired to this channel?)")
    d = np.diff(rise)
    med = float(np.median(d))
    period0 = float(d[np.abs(d - med) < 0.3 * med].mean())  # samples; a mean of many edges, not one (edges are +-0.5)
    expected = sample_rate_hz / nominal_fps
    if not 0.8 < period0 / expected < 1.25:
        raise InputError(source, f"strobe period {period0 / sample_rate_hz * 1e3:.4g} ms does not match the camera's "
                                 f"{nominal_fps:g} fps ({1e3 / nominal_fps:.4g} ms)")
    k_rise = np.round((rise - rise[0]) / period0).astype(int)
    for _ in range(2):  # refine the period on the numbered pulses, then number them again
        period0 = float(np.polyfit(k_rise, rise, 1)[0])
        k_rise = np.round((rise - rise[0]) / period0).astype(int)
    flags: list[str] = []
    notes: list[str] = []
    if np.any(np.diff(k_rise) != 1):
        missing = int(k_rise[-1] + 1 - k_rise.size)
        flags.append("strobe_gaps")
        notes.append(f"{missing} strobe pulse(s) missing (lost DAQ samples?)")
    # Pair each falling edge with the rising edge before it, one period at most.
    j = np.searchsorted(rise, fall) - 1
    good = (j >= 0) & (fall - rise[np.clip(j, 0, None)] < period0)
    fall, k_fall = fall[good], k_rise[j[good]]
    a, b, e, res = _fit_lines(rise, k_rise, fall, k_fall)
    for _ in range(2):  # drop edges a glitch moved (more than a fifth of a frame off the line)
        r_res = rise - (a + b * k_rise)
        f_res = fall - (a + e + b * k_fall)
        keep_r, keep_f = np.abs(r_res) < 0.2 * b, np.abs(f_res) < 0.2 * b
        if keep_r.all() and keep_f.all():
            break
        rise, k_rise, fall, k_fall = rise[keep_r], k_rise[keep_r], fall[keep_f], k_fall[keep_f]
        a, b, e, res = _fit_lines(rise, k_rise, fall, k_fall)
    n_samples = len(volts)
    k_last = int(k_rise.max())
    last_end = a + e + b * k_last
    # The pulse numbers of counter 0, by the end of the strobe and by the trigger.
    k0_end = k_last - int(counters.max()) if n_samples - 1 - last_end > 2 * b else None
    k0_trig = None
    if trigger_time_s is not None:
        # The DAQ trigger sample is the first at or above the level: the crossing lies up to a sample earlier.
        earliest = (trigger_time_s + trigger_delay_s - t0_s) * sample_rate_hz - 1.0
        k0_trig = int(np.ceil((earliest - a) / b - 1e-9))
        if abs((a + b * k0_trig) - earliest) < 1.0 or abs((a + b * (k0_trig - 1)) - earliest) < 1.0:
            flags.append("trigger_anchor_ambiguous")
    if k0_end is not None:
        k0, anchor = k0_end, "end"
        if k0_trig is not None and k0_trig != k0_end and "trigger_anchor_ambiguous" not in flags:
            flags.append("anchor_mismatch")
            notes.append(f"the strobe's end puts counter 0 {k0_end - k0_trig:+d} pulse(s) from the trigger's choice")
    elif k0_trig is not None:
        k0, anchor = k0_trig, "trigger"
    else:
        raise InputError(source, "cannot tell which strobe pulse is the trigger frame: the strobe runs to the end of "
                                 "the record and the take has no trigger time")
    return StrobeTiming(
        frame0_start_s=t0_s + (a + b * k0) / sample_rate_hz,
        period_s=b / sample_rate_hz,
        exposure_s=e / sample_rate_hz,
        n_pulses=int(k_rise.size),
        residual_frames=res / b,
        anchor=anchor,
        flags=tuple(flags),
        notes=tuple(notes),
    )


def _fit_lines(rise: np.ndarray, k_rise: np.ndarray, fall: np.ndarray, k_fall: np.ndarray):
    """Least squares for rise_k = a + b k and fall_k = a + e + b k: returns a, b, e and the rms residual."""
    A = np.zeros((rise.size + fall.size, 3))
    A[:, 0] = 1.0
    A[:, 1] = np.concatenate([k_rise, k_fall])
    A[rise.size:, 2] = 1.0
    y = np.concatenate([rise, fall])
    if fall.size == 0:
        A, y = A[:, :2], y
        (a, b), *_ = np.linalg.lstsq(A, y, rcond=None)
        e = np.nan
        res = y - A @ np.array([a, b])
    else:
        (a, b, e), *_ = np.linalg.lstsq(A, y, rcond=None)
        res = y - A @ np.array([a, b, e])
    return float(a), float(b), float(e), float(np.sqrt(np.mean(res ** 2)))


__all__ = ["StrobeTiming", "fit_strobe", "strobe_edges"]
