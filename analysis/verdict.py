"""Verdicts on the video's numbers: the MAC target over the modes the video can resolve (those above its noise
floor, analysis/noise.py), and the 2D cross-check's gain and correlation against what its tracks' noise allows.

Thresholds, measured on the simulated capture of tests/analysis/test_run.py (3 views, 400x300 px, the 3D motion
hil_sim's exact one, docs/analysis.md): the cross-check reads gains 0.64-0.95 and correlations 0.82-0.94 of what
its tracks' noise allows (0.95-0.99); with 14 um of white noise on every point (a real reconstruction's, on the
rig's static base) gains 0.54-0.67 and 0.72-0.85 of it. A reconstruction whose motion is 2-3x the truth on the
points it says move most (docs/analysis.md, the 256 px bench) read correlations 0.18-0.45.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MIN_MAC = 0.9                    # the MAC target, over the modes above the video's noise floor
CROSSCHECK_GAIN = (0.5, 1.5)     # the median gain tracked / 3D: exact 3D motion reads 0.64-0.95
CROSSCHECK_CORRELATION = 0.7     # the median correlation, as a fraction of what the tracks' noise allows
CROSSCHECK_MIN_EXPECTED = 0.5    # below this expected correlation the images cannot show the motion: not judged


@dataclass(frozen=True)
class Verdict:
    """A target judged: "met", "not met" or "not judged", the sentence that says so, and its numbers."""

    status: str
    line: str
    details: dict = field(default_factory=dict)

    def summary(self) -> dict:
        return {"status": self.status, "line": self.line, **self.details}


def mac_verdict(freq_hz, pair_mac, below_floor, min_mac: float = MIN_MAC) -> Verdict:
    """MAC >= min_mac for every mode above the noise floor; the modes below it are listed apart, not judged."""
    f, m, b = np.asarray(freq_hz, float), np.asarray(pair_mac, float), np.asarray(below_floor, bool)
    apart = "; below the video's noise floor, not judged: " + ", ".join(
        f"{fi:.1f} Hz (MAC {mi:.2f})" for fi, mi in zip(f[b], m[b])) if b.any() else ""
    details = {"min_mac": min_mac, "judged_hz": f[~b].tolist(), "below_floor_hz": f[b].tolist(),
               "worst_mac": float(m[~b].min()) if (~b).any() else None}
    if not (~b).any():
        return Verdict("not judged", f"MAC: no mode stands above the video's noise floor{apart}", details)
    k = int(np.argmin(np.where(b, np.inf, m)))
    failing = [f"{fi:.1f} Hz ({mi:.3f})" for fi, mi, bi in zip(f, m, b) if not bi and mi < min_mac]
    if failing:
        return Verdict("not met", f"MAC below {min_mac:g} at {', '.join(failing)} of the {int((~b).sum())} modes "
                       f"above the video's noise floor{apart}", details)
    return Verdict("met", f"MAC >= {min_mac:g} for all {int((~b).sum())} modes above the video's noise floor "
                   f"(lowest {m[k]:.3f} at {f[k]:.1f} Hz){apart}", details)


def crosscheck_verdict(checks) -> Verdict | None:
    """The 2D cross-check over its views (medians): gain within CROSSCHECK_GAIN and correlation at least
    CROSSCHECK_CORRELATION of what the tracks' noise allows; not judged when the motion is below that noise."""
    if not checks:
        return None
    gain = float(np.median([c.gain for c in checks]))
    corr = float(np.median([c.correlation for c in checks]))
    exp = [c.expected_correlation for c in checks]
    expected = float(np.median([e for e in exp if np.isfinite(e)])) if any(np.isfinite(e) for e in exp) else 1.0
    noise = [c.noise_px for c in checks if np.isfinite(c.noise_px)]
    details = {"gain_median": gain, "correlation_median": corr, "expected_correlation": expected,
               "noise_px_median": float(np.median(noise)) if noise else None,
               "motion_rms_px_median": float(np.median([c.motion_rms_px for c in checks])),
               "gain_range": list(CROSSCHECK_GAIN), "correlation_fraction": CROSSCHECK_CORRELATION}
    need = CROSSCHECK_CORRELATION * expected
    head = f"2D cross-check: gain {gain:.2f} (expected {CROSSCHECK_GAIN[0]:g}-{CROSSCHECK_GAIN[1]:g}), " \
           f"correlation {corr:.2f} (at least {need:.2f}: {CROSSCHECK_CORRELATION:g} x the {expected:.2f} the " \
           "tracks' noise allows)"
    if expected < CROSSCHECK_MIN_EXPECTED:
        return Verdict("not judged", f"{head}: the motion is below the tracks' noise; nothing to judge", details)
    ok_gain = CROSSCHECK_GAIN[0] <= gain <= CROSSCHECK_GAIN[1]
    ok_corr = corr >= need
    if ok_gain and ok_corr:
        return Verdict("met", f"{head}: the 3D motion agrees with the images", details)
    why = [w for w, ok in (("gain", ok_gain), ("correlation", ok_corr)) if not ok]
    return Verdict("not met", f"{head}: the 3D motion does not agree with the images ({' and '.join(why)})",
                   details)
