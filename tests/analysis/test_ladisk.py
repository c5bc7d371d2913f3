"""Modal fits on LADISK's free-free steel beam: the hammer-accelerometer FRF (LSCF + LSFD) and the camera (LSFD)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from odsplat.analysis.ema import fit_modes, lsfd
from odsplat.analysis.frf import FRFSettings, estimate_frf
from odsplat.spine.io.signals import read_signals

FOLDER = "ladisk-imaging-tutorial"
KNOWN_HZ = np.array([695.8, 1898.0, 3671.2])  # sdypy-EMA LSCF, from the data's README
KNOWN_DAMPING = np.array([0.0047, 0.0031, 0.0020])
EXTRA_HZ = 2777.6  # a weak but stable mode (0.24 %) that the README's pick leaves out
BAND_HZ = (100.0, 5000.0)
PRE_SAMPLES = 30  # LVM samples before the trigger, which also started the camera
CAMERA_FPS = 15000.0
# The README says the array is in px (8e-5 m/px), but its values are metres already: as px the beam would
# move a few nm where the accelerometer measures tens of um, and as metres the camera receptance comes out
# at the README's 0.66-0.72 of the accelerometer's (asserted below).
DISP_UNIT_M = 1.0


def _h1(response: np.ndarray, force: np.ndarray, sample_rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """H1 of the one hit over the whole record, force window on, no exponential window (the record is long
    enough for the response to decay)."""
    frf = estimate_frf(force, response, sample_rate_hz, FRFSettings(exponential_end=None))
    assert frf.n_averages == 1
    return frf.freq_hz, frf.h1[:, 0]


def _signals(path):
    sig = read_signals(path)
    assert [c.name for c in sig.channels] == ["Acceleration (Trigger)", "Force (Trigger)"]
    assert sig.sample_rate_hz == 50000.0 and sig.n_samples == 50030
    acc, force = (c.values.astype(float) for c in sig.channels)
    return sig.sample_rate_hz, acc, force


@pytest.fixture(scope="module")
def accelerometer_frf(shared_data):
    fs, acc, force = _signals(shared_data / FOLDER / "acceleration.lvm")
    return _h1(acc, force, fs)  # accelerance, (m/s^2)/N


@pytest.fixture(scope="module")
def accelerometer_fit(accelerometer_frf):
    freq_hz, h = accelerometer_frf
    return fit_modes(freq_hz, h, frf_kind="accelerance", fmin_hz=BAND_HZ[0], fmax_hz=BAND_HZ[1])


def test_accelerometer_modes_match_the_published_fit(accelerometer_fit):
    fit = accelerometer_fit
    expected = np.sort(np.append(KNOWN_HZ, EXTRA_HZ))
    assert fit.n_modes == 4, fit.freq_hz
    assert np.max(np.abs(fit.freq_hz / expected - 1)) < 0.001  # measured: 695.73, 1898.08, 2777.57, 3671.18 Hz
    known = [0, 1, 3]  # no window was applied, so the damping needs no correction
    assert np.max(np.abs(fit.damping[known] / KNOWN_DAMPING - 1)) < 0.10  # measured: 0.463, 0.305, 0.202 %
    assert np.all(fit.lsfd.fit_error < 0.05)
    # The mode shapes of one accelerometer are its (complex) residues; each has a clear magnitude.
    assert np.all(np.abs(fit.shapes[:, 0]) > 10 * fit.lsfd.residue_std)


def _camera_receptance(folder) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera displacement (m) over hammer force (N) at the video's 4 Hz lines up to 3 kHz, (F, 15), and the
    accelerometer's receptance of the same hit on the same lines, (F,)."""
    disp = np.load(folder / "displacements_lk.npy")
    assert disp.shape == (15, 3750, 2)
    freq_hz = np.fft.rfftfreq(disp.shape[1], 1 / CAMERA_FPS)
    spectra = np.abs(np.fft.rfft(disp - disp.mean(axis=1, keepdims=True), axis=1)).sum(axis=0)
    # The beam moves along image axis 0 (y): its band 600-800 Hz stands far above the median there; axis 1
    # holds tracking noise and drift (and the larger variance, so variance would pick the wrong axis).
    band = (freq_hz > 600) & (freq_hz < 800)
    prominence = spectra[band].max(axis=0) / np.median(spectra[band], axis=0)
    assert prominence[0] > 5 and prominence[1] < 2, prominence
    disp_m = disp[:, :, 0] * DISP_UNIT_M
    # The camera started at the trigger: take 0.25 s of force from there, and scale both DFTs by their own
    # sample step, so that both are Fourier transforms on the same 4 Hz lines.
    fs, acc, force = _signals(folder / "camera.lvm")
    record = slice(PRE_SAMPLES, PRE_SAMPLES + round(disp.shape[1] / CAMERA_FPS * fs))
    n = int(np.count_nonzero(freq_hz <= 3000))
    force_ft = np.fft.rfft(force[record])[:n] / fs
    disp_ft = np.fft.rfft(disp_m, axis=1)[:, :n] / CAMERA_FPS
    assert np.allclose(np.fft.rfftfreq(record.stop - record.start, 1 / fs)[:n], freq_hz[:n])
    with np.errstate(divide="ignore", invalid="ignore"):
        acc_receptance = np.fft.rfft(acc[record])[:n] / fs / force_ft / -(2 * np.pi * freq_hz[:n]) ** 2
    return freq_hz[:n], (disp_ft / force_ft[None, :]).T, acc_receptance


def _sign_changes(shape: np.ndarray, significant: np.ndarray) -> int:
    s = np.sign(shape[significant])
    return int(np.count_nonzero(s[1:] != s[:-1]))


def test_camera_mode_shapes_from_the_accelerometer_poles(shared_data, accelerometer_fit):
    freq_hz, h, acc_receptance = _camera_receptance(shared_data / FOLDER)
    # Camera over accelerometer at the two peaks, at the largest-moving point (the first): measured 0.66 and
    # 0.72 in magnitude, -22 and +9 degrees in phase. Force taken from sample 0 instead of the trigger would
    # turn the phase by 150 and 410 degrees: the video did start at the trigger.
    peaks = [np.argmin(np.abs(freq_hz - f)) for f in (696, 1900)]
    assert np.all(np.argmax(np.abs(h[peaks]), axis=1) == 0)
    ratio = h[peaks, 0] / acc_receptance[peaks]
    assert np.all((np.abs(ratio) > 0.6) & (np.abs(ratio) < 0.8)), ratio
    assert np.all(np.abs(np.angle(ratio, deg=True)) < 30), ratio
    fit = accelerometer_fit
    poles = fit.poles_rad_s[[np.argmin(np.abs(fit.freq_hz - f)) for f in KNOWN_HZ[:2]]]
    cam = lsfd(freq_hz, h, poles, frf_kind="receptance", fmin_hz=300, fmax_hz=3000)
    assert cam.residues.shape == (2, 15)
    # Both modes stand well clear of the fit's noise: RMS residue over RMS standard error (measured 37, 17).
    snr = np.sqrt(np.mean(np.abs(cam.residues) ** 2, axis=1) / np.mean(cam.residue_std**2, axis=1))
    assert np.all(snr > 8), snr
    shapes = cam.normal_mode_shapes()
    shapes = shapes / np.abs(shapes).max(axis=1, keepdims=True)
    significant = np.abs(cam.residues) > 3 * cam.residue_std
    # 696 Hz, first bending of a free-free beam: two nodes, both ends in phase and the middle against them
    # (measured: 1, .70, .39, .08, -.20 ... -.66 ... -.22, .03, .34).
    first = shapes[0]
    assert _sign_changes(first, significant[0]) == 2
    assert first[0] > 0.9 and first[-1] > 0.2 and first[7] < -0.5
    assert np.max(np.abs(np.diff(first))) < 0.35  # smooth along the beam
    # 1898 Hz, second bending: the data shows two sign changes; the shape falls from .75 to .16 over the
    # last three points, so its third node lies just past the last tracked point.
    second = shapes[1]
    assert _sign_changes(second, significant[1]) == 2
    assert second[0] > 0.9 and second[4] < -0.5 and second[11] > 0.5 and 0 < second[-1] < 0.4
    assert np.max(np.abs(np.diff(second))) < 0.6
    # The modes are (nearly) real: points clear of the noise lie within 0.3 rad of the mode's real line
    # (measured: 13 and 10 points, at most 0.09 and 0.07 rad off).
    for r in range(2):
        psi = cam.residues[r] * np.exp(-0.5j * np.angle(np.sum(cam.residues[r] ** 2)))
        strong = np.abs(cam.residues[r]) > 10 * cam.residue_std[r]
        off = np.abs(np.angle(psi[strong] * np.sign(psi[strong].real)))
        assert strong.sum() >= 8 and off.max() < 0.3, off


def test_frequencies_match_sdypy(accelerometer_frf, accelerometer_fit):
    ema = pytest.importorskip("sdypy.EMA")
    freq_hz, h = accelerometer_frf
    model = ema.Model(frf=h[None, :], freq=freq_hz, lower=BAND_HZ[0], upper=BAND_HZ[1], pol_order_high=50,
                      frf_form="accelerance")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.get_poles(show_progress=False)
        model.select_closest_poles(list(KNOWN_HZ))
    ours = accelerometer_fit.freq_hz[[np.argmin(np.abs(accelerometer_fit.freq_hz - f)) for f in KNOWN_HZ]]
    assert np.max(np.abs(ours / np.asarray(model.nat_freq) - 1)) < 0.001
    assert np.max(np.abs(np.asarray(model.nat_xi) / KNOWN_DAMPING - 1)) < 0.10
