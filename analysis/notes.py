"""What the analysis's numbers cannot show, as findings: one small frozen dataclass per kind, collected while it
analyses (analyze.py), each worded here and only here (its `text`). analysis.json's notes, the terminal's summary
and the report's top are these words."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .band import CUT_PEAK_DB, FORCE_DROP_DB, MAX_FRACTION_OF_RATE, frf_peaks, unmatched_peaks
from .frf import FRFResult


def length_text(x_m: float) -> str:
    """A length in the unit that reads best: 3 significant digits in nm, µm, mm or m."""
    for unit, scale in (("nm", 1e-9), ("µm", 1e-6), ("mm", 1e-3)):
        if abs(x_m) < 1000 * scale:
            return f"{x_m / scale:.3g} {unit}"
    return f"{x_m:.3g} m"


# ---------------------------------------------------------------------------------------------- the accelerometers

@dataclass(frozen=True)
class PeaksWithoutMode:
    """Clear FRF peaks inside the fit band with no mode near them (band.unmatched_peaks)."""

    peaks: tuple[tuple[float, float], ...]   # (frequency in Hz, height in dB against the highest), by frequency

    @property
    def text(self) -> str:
        return ("clear FRF peaks with no mode: " + ", ".join(f"{f:.1f} Hz ({h:+.0f} dB)" for f, h in self.peaks)
                + "; pick them with --freq (analyze.approx_freq_hz) or raise max_order")


@dataclass(frozen=True)
class PeaksOutsideBand:
    """Strong FRF peaks the fit band leaves out."""

    fmin_hz: float
    fmax_hz: float
    peaks_hz: tuple[float, ...]
    force_drop_db: float | None    # why the band ends there: the hammer's force is this far down; None: it was given

    @property
    def text(self) -> str:
        why = ("the band was given" if self.force_drop_db is None else
               f"the hammer's force is {self.force_drop_db:g} dB down above {self.fmax_hz:.0f} Hz")
        return (f"strong FRF peaks outside the fit band {self.fmin_hz:.0f}-{self.fmax_hz:.0f} Hz ({why}): "
                + ", ".join(f"{f:.0f} Hz" for f in self.peaks_hz)
                + "; widen it with --fmax (analyze.fmax_hz); a harder hammer tip excites higher")


@dataclass(frozen=True)
class UnplacedSensors:
    """Response channels without a position or direction: no shapes."""

    names: tuple[str, ...]

    @property
    def text(self) -> str:
        return (f"no position or direction for {', '.join(self.names)}: frequencies and damping only; shapes need "
                "them (`odsplat geometry CAPTURE FILE`)")


# ---------------------------------------------------------------------------------------------- the video

@dataclass(frozen=True)
class ModesAboveVideoBand:
    """Accelerometer modes above the frequencies the video's timesteps resolve."""

    freq_hz: tuple[float, ...]

    @property
    def text(self) -> str:
        return f"modes at {', '.join(f'{f:.0f}' for f in self.freq_hz)} Hz are above the video's band: no video shape"


@dataclass(frozen=True)
class WindowTooShort:
    """A mode below the noise floor whose cause is the video's window: too few of its cycles to read its shape."""

    mode: int                # its number (1-based, as the accelerometer modes are numbered)
    freq_hz: float
    window_s: float
    min_cycles: float        # what a shape needs

    @property
    def cycles(self) -> float:
        return self.window_s * self.freq_hz

    @property
    def text(self) -> str:
        return (f"mode {self.mode} ({self.freq_hz:.1f} Hz): the video's window ({1e3 * self.window_s:.1f} ms) holds "
                f"{self.cycles:.2f} of its cycles, too few to read its shape apart from the other modes (MAC and "
                f"scale not judged); reconstruct at least {1e3 * self.min_cycles / self.freq_hz:.0f} ms "
                "([reconstruct] n_timesteps)")


@dataclass(frozen=True)
class BelowNoiseFloor:
    """A mode below the video's noise floor: its amplitude at the sensors below the floor there, or (full_field_mac
    given) above it there but too small over the whole structure. Its MAC is not judged."""

    mode: int
    freq_hz: float
    amplitude_m: float
    floor_m: float
    expected_mac: float      # the MAC the noise alone allows its shape at the sensors
    real: bool               # its shape is a real mode (which keeps half the noise)
    full_field_mac: float | None = None   # set where only the full structure puts it below: the MAC allowed there

    @property
    def text(self) -> str:
        half = " (a little more once its shape is taken as a real mode)" if self.real else ""
        if self.full_field_mac is not None:
            return (f"mode {self.mode} ({self.freq_hz:.1f} Hz): above the video's noise floor at the sensors "
                    f"({length_text(self.amplitude_m)} against {length_text(self.floor_m)}), but over the whole "
                    f"structure, where most of its motion is smaller, the noise allows its shape a MAC of only "
                    f"{self.full_field_mac:.2f}, too little to judge (MAC and scale not judged)")
        return (f"mode {self.mode} ({self.freq_hz:.1f} Hz): below the video's noise floor "
                f"({length_text(self.amplitude_m)} against {length_text(self.floor_m)} at the sensors): the noise "
                f"alone allows its shape a MAC of {self.expected_mac:.2f}{half}, too little to judge (MAC and "
                "scale not judged)")


@dataclass(frozen=True)
class ModesNotSeparated:
    """Modes above the noise floor whose poles are too close for the video's record to separate their shapes."""

    modes: tuple[int, ...]
    freq_hz: tuple[float, ...]
    gain: tuple[float, ...]             # each one's fit gain over its gain alone (noise.separation_gains)
    record_needed_s: tuple[float, ...]  # the record that would separate it (inf: none up to 64 x this one)
    window_s: float
    max_gain: float

    @property
    def text(self) -> str:
        modes = ", ".join(f"{m} ({f:.1f} Hz)" for m, f in zip(self.modes, self.freq_hz))
        gains = "/".join(f"{g:.1f}" for g in self.gain)
        need = max(self.record_needed_s)
        fix = (f"a video record of at least {1e3 * need:.0f} ms separates them (the takes' length, and [reconstruct] "
               "n_timesteps where it is set)"
               if np.isfinite(need) else "their motion dies out before any record separates them: a second hit "
               "point that excites one more than the other, or a sensor at a node of one, can")
        return (f"modes {modes}: too close to one another for the video's {1e3 * self.window_s:.0f} ms window (the "
                f"fit reads them with {gains} x the gain each has alone, above {self.max_gain:g}): their shapes mix, "
                f"and any error of the motion is amplified as much (MAC and scale not judged); {fix}")


@dataclass(frozen=True)
class ComplexMode:
    """A video mode whose shape is complex beyond its noise: kept complex."""

    mode: int
    freq_hz: float
    mpc: float
    lost: float              # the share of its shape out of phase
    quadrature_ratio: float  # that, over what the noise puts there

    @property
    def text(self) -> str:
        return (f"mode {self.mode} ({self.freq_hz:.1f} Hz): a complex mode in the video (MPC {self.mpc:.2f}; "
                f"{100 * self.lost:.0f} % of its shape out of phase, {self.quadrature_ratio:.1f} x what the noise "
                "puts there): its shape is left complex, with the noise's full power; a time shift between views or "
                "non-proportional damping does this")


@dataclass(frozen=True)
class OdsCarriedByNoise:
    """An ODS line the video's modes below the noise floor carry: the video's ODS there is their noise."""

    line: int                # its number (1-based)
    freq_hz: float
    share: float             # their terms' size at the sensors over the ODS's

    @property
    def text(self) -> str:
        return (f"ODS line {self.line} ({self.freq_hz:.1f} Hz): the video's ODS there is carried by modes below its "
                f"noise floor (their terms sum to {min(self.share, 99.0):.2g} x its size at the sensors); read it "
                "from the accelerometers")


@dataclass(frozen=True)
class ModesNotDiscriminated:
    """Modes whose MAC reaches the target but whose reference shapes the sensors cannot tell from another mode's
    (verdict.DISCRIMINATION): their MAC does not show which of the two shapes the video found."""

    modes: tuple[int, ...]                        # their numbers
    pairs: tuple[tuple[int, int, float], ...]     # (mode, mode, reference AutoMAC), each pair once
    n_sensors: int
    threshold: float

    @property
    def text(self) -> str:
        many = len(self.modes) > 1
        return (f"mode{'s' if many else ''} {', '.join(str(k) for k in self.modes)}: the {self.n_sensors} sensors "
                f"cannot tell {'each' if many else 'it'} from another mode (reference AutoMAC above "
                f"{self.threshold:g}: {', '.join(f'{i}/{j} {a:.2f}' for i, j, a in self.pairs)}), so the MAC does "
                "not show which shape the video found: not discriminated, not met; sensors at other points or along "
                "other directions would tell them apart (the report's AutoMAC table)")


MIN_SENSOR_R2 = 0.3   # below this share of a sensor's video motion explained by the modes (adjusted for the fit's
#                       parameters: 0 for noise alone), the video does not see it move. Raw shares on hil_sim
#                       (bench/fidelity.py): 0.02-0.06 on the frame and mast (members 4-7 px across, 241-256
#                       timesteps: noise alone explains 0.04-0.05 there), 0.6-0.99 on the arm and the plate


@dataclass(frozen=True)
class SensorsNotSeen:
    """Sensors where the modes explain little of the video's motion: the reconstruction does not see the structure
    move there, and what it reads is its noise."""

    names: tuple[str, ...]
    r2: tuple[float, ...]          # adjusted R^2 of the modes' fit to the video's motion there (0: noise alone)

    @property
    def text(self) -> str:
        return ("the video's motion at " + ", ".join(f"{n} ({100 * r:.0f} %)" for n, r in zip(self.names, self.r2))
                + " is hardly the modes' (the share they explain beyond what they would of noise alone): the "
                "reconstruction does not see the structure move "
                "there (too few pixels across it, or too little texture), so its shapes there are its noise; film "
                "closer or with a finer texture")


Note = (PeaksWithoutMode | PeaksOutsideBand | UnplacedSensors | ModesAboveVideoBand | WindowTooShort
        | BelowNoiseFloor | ModesNotSeparated | ComplexMode | OdsCarriedByNoise | ModesNotDiscriminated
        | SensorsNotSeen)


def band_findings(frf: FRFResult, band_hz: tuple[float, float], freq_hz: np.ndarray, *, given: bool,
                  inside: list | None = None) -> list[Note]:
    """What the FRFs say of the fit band and the poles: clear peaks in the band with no mode, and strong peaks the
    band leaves out (`given`: whether the user chose it); `inside`: the band's clear peaks where already found
    (band.frf_peaks)."""
    fmin, fmax = band_hz
    df = float(frf.freq_hz[1] - frf.freq_hz[0]) if len(frf.freq_hz) > 1 else 0.0
    out: list[Note] = []
    missed = unmatched_peaks(frf_peaks(frf, fmin, fmax) if inside is None else inside, freq_hz, df)
    if missed:
        out.append(PeaksWithoutMode(tuple((p.freq_hz, p.height_db) for p in sorted(missed, key=lambda p: p.freq_hz))))
    nyq = min(MAX_FRACTION_OF_RATE * frf.sample_rate_hz, float(frf.freq_hz[-1]))
    everywhere = frf_peaks(frf, float(frf.freq_hz[0]), nyq, height_db=None) if nyq > frf.freq_hz[0] else []
    if everywhere:   # heights relative to one reference: the highest clear peak below 0.4 x the rate
        band_top = max((p.height_db for p in everywhere if fmin <= p.freq_hz <= fmax), default=-np.inf)
        cut = [p for p in everywhere if not fmin <= p.freq_hz <= fmax and p.height_db >= band_top - CUT_PEAK_DB]
        if cut:
            out.append(PeaksOutsideBand(float(fmin), float(fmax), tuple(sorted(p.freq_hz for p in cut)),
                                        None if given else FORCE_DROP_DB))
    return out


__all__ = ["BelowNoiseFloor", "ComplexMode", "ModesAboveVideoBand", "ModesNotDiscriminated", "ModesNotSeparated",
           "Note", "OdsCarriedByNoise", "PeaksOutsideBand", "PeaksWithoutMode", "UnplacedSensors", "WindowTooShort",
           "band_findings", "length_text"]
