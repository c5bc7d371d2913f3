"""The video's noise floor against Monte Carlo: a mode at its floor, read through the decay fit the analysis makes,
must have the MAC the floor promises and must pass the MAC verdict on noise alone (analysis/noise.py)."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.analysis.correlation import mac
from odsplat.analysis.noise import (
    FLOOR_MAC,
    FLOOR_SIGMAS,
    MAX_LOST,
    MAX_SEPARATION_GAIN,
    design_gains,
    full_field_expected_mac,
    noise_floor,
    real_modes,
    record_needed_s,
    separation_gains,
)
from odsplat.analysis.ods import fit_decay
from odsplat.analysis.verdict import MIN_MAC
from odsplat.hil_sim.structure import ModalStructure

FPS = 2000.0
T_MIN_S = 1.5e-3


def test_a_mode_at_its_floor_has_the_mac_the_floor_promises_and_passes_the_verdict():
    """The demo's record (247 timesteps at 2000 fps) and hil_sim's six poles, six sensors, white noise of 5 um on
    every channel; the 371 Hz mode's rms amplitude over the sensors set to its floor, the others well above. Over
    400 draws the floor read from the residual is the one set, the weak mode's mean MAC is FLOOR_MAC, and noise alone
    fails MAC >= 0.9 in 0.25 % of draws (measured; 28 % at 3 sigma, the floor until 2026-11-26)."""
    rng = np.random.default_rng(0)
    s = ModalStructure()
    wn = 2 * np.pi * np.asarray(s.freqs_hz)
    z = np.asarray(s.dampings)
    poles = -z * wn + 1j * wn * np.sqrt(1 - z ** 2)
    t = np.arange(-1, 246) / FPS
    n_s, n_p, sigma = 6, 40, 5e-6
    shapes = rng.normal(size=(len(poles), n_s))
    shapes /= np.sqrt(np.mean(shapes ** 2, axis=1, keepdims=True))          # rms 1 over the sensors
    weak = len(poles) - 1
    # the floor the analysis will compute: calibrate once on noise alone (the design's gain for each mode)
    probe = noise_floor(t, rng.normal(0, sigma, (len(t), n_s)), rng.normal(0, sigma, (len(t), 3 * n_p)),
                        fit_decay(t, rng.normal(0, sigma, (len(t), n_s + 3 * n_p)), poles, t_min_s=T_MIN_S))
    amp = np.full(len(poles), 20 * probe.mode_floor_m[weak])
    amp[weak] = probe.mode_floor_m[weak]
    after = np.clip(t, 0, None)
    phase = rng.uniform(0, 2 * np.pi, len(poles))
    clean = np.einsum("rt,rs->ts", amp[:, None] * np.exp(poles.real[:, None] * after)
                      * np.cos(poles.imag[:, None] * after + phase[:, None]) * (t >= 0), shapes)
    macs, floors, expected = [], [], []
    for _ in range(400):
        sensors = clean + rng.normal(0, sigma, clean.shape)
        surface = rng.normal(0, sigma, (len(t), 3 * n_p))                  # static points: noise only
        fit = fit_decay(t, np.concatenate([sensors, surface], axis=1), poles, t_min_s=T_MIN_S)
        nf = noise_floor(t, sensors, surface, fit)
        macs.append(float(mac(fit.amplitudes[weak, :n_s], shapes[weak])[0, 0]))
        floors.append(nf.mode_floor_m[weak])
        expected.append(nf.expected_mac[weak])
    macs = np.asarray(macs)
    assert FLOOR_SIGMAS ** 2 / (FLOOR_SIGMAS ** 2 + 1) == pytest.approx(FLOOR_MAC)
    assert abs(np.median(floors) / amp[weak] - 1) < 0.05, np.median(floors) / amp[weak]
    assert abs(np.median(expected) - FLOOR_MAC) < 0.01, np.median(expected)
    assert abs(macs.mean() - FLOOR_MAC) < 0.02, macs.mean()
    assert np.mean(macs < MIN_MAC) < 0.04, np.mean(macs < MIN_MAC)


def _decay_record(rng, shapes, amp, phase_rad, sigma):
    """The demo's record and hil_sim's poles: channels x(t) = amp e^(sigma t) cos(w t + phase) shape, plus white
    noise of sigma; shapes (R, K), complex where a channel's own phase differs (its angle adds to the mode's)."""
    s = ModalStructure()
    wn = 2 * np.pi * np.asarray(s.freqs_hz)
    z = np.asarray(s.dampings)
    poles = -z * wn + 1j * wn * np.sqrt(1 - z ** 2)
    t = np.arange(-1, 246) / FPS
    after = np.clip(t, 0, None)
    arg = poles.imag[:, None, None] * after[None, :, None] + phase_rad[:, None, None] + np.angle(shapes)[:, None]
    env = np.exp(poles.real[:, None, None] * after[None, :, None]) * (t >= 0)[None, :, None]
    clean = np.sum(amp[:, None, None] * np.abs(shapes)[:, None] * env * np.cos(arg), axis=0)     # (T, K)
    return t, poles, clean + rng.normal(0, sigma, clean.shape)


def test_real_modes_drop_the_noise_out_of_phase_and_keep_a_complex_mode_complex():
    """Real shapes (300 channels, each mode 10x its noise per channel in amplitude, a phase of its own) through the
    decay fit: every mode is judged real, the energy out of phase is the noise's (within 15 %), the common phase is
    found, and the projection halves the shapes' error energy. A mode whose shape turns by 40 degrees over half
    its channels is judged complex and left as it is."""
    rng = np.random.default_rng(3)
    sigma, K, R = 5e-6, 300, 6
    shapes = rng.normal(size=(R, K))
    shapes /= np.sqrt(np.mean(shapes ** 2, axis=1, keepdims=True))
    phase = rng.uniform(-np.pi, np.pi, R)
    ratios, errors = [], []
    for _ in range(20):
        t, poles, x = _decay_record(rng, shapes.astype(complex), np.full(R, 10 * sigma), phase, sigma)
        fit, nf = _fit(t, x, poles)
        rm = real_modes(fit, t, 2 + np.arange(K), nf.point_sigma_m, nf.spectrum_gain)
        assert rm.real.all() and np.all(rm.mpc > 0.9), (rm.mpc, rm.quadrature_ratio, rm.lost)
        assert np.allclose(np.cos(2 * (rm.phase_rad - phase)), 1, atol=0.01)   # the phase, up to a sign
        ratios.append(rm.quadrature_ratio)
        truth = 10 * sigma * shapes * np.exp(1j * phase)[:, None]
        errors.append([np.sum(np.abs(2 * a[:, 2:] - truth) ** 2) for a in (fit.amplitudes, rm.apply(fit.amplitudes))])
    assert np.all(np.abs(np.mean(ratios, axis=0) - 1) < 0.15), np.mean(ratios, axis=0)
    after, before = np.sum(errors, axis=0)[::-1]
    assert 0.4 < after / before < 0.6, after / before
    # a complex mode: half of mode 1's channels 40 degrees behind the others
    turned = shapes.astype(complex)
    turned[0, K // 2:] *= np.exp(-1j * np.deg2rad(40))
    t, poles, x = _decay_record(rng, turned, np.full(R, 10 * sigma), phase, sigma)
    fit, nf = _fit(t, x, poles)
    rm = real_modes(fit, t, 2 + np.arange(K), nf.point_sigma_m, nf.spectrum_gain)
    assert not rm.real[0] and rm.real[1:].all(), rm.real
    assert rm.lost[0] > MAX_LOST and rm.mpc[0] < 0.9
    assert np.array_equal(rm.apply(fit.amplitudes)[0], fit.amplitudes[0])


def _fit(t, x, poles):
    """The decay fit and its noise floor as the analysis makes them, the first two channels as the sensors."""
    fit = fit_decay(t, np.concatenate([x[:, :2], x], axis=1), poles, t_min_s=T_MIN_S)
    return fit, noise_floor(t, x[:, :2], x, fit, point_components=1)


# ---------------------------------------------------------------------------------------------- separation

def _close_pair(record_s: float, rng, drift: float = 0.1):
    """The mast's pair (40.8 and 42.1 Hz, 2500 fps) over record_s, 6 sensors and 20 points, each channel's gain
    drifting by its own few per cent over 0.1 s (an error of the motion that is not white noise, as a view's gain
    that changes over the record is) and white noise 100x below the motion."""
    f, z = np.array([40.8, 42.1]), np.array([0.008, 0.007])
    poles = -z * 2 * np.pi * f + 1j * 2 * np.pi * f * np.sqrt(1 - z ** 2)
    shapes = np.random.default_rng(1).normal(size=(2, 6 + 60))
    t = np.arange(-1, int(record_s * 2500)) / 2500
    after = np.clip(t, 0, None)
    q = np.exp(poles.real[:, None] * after) * np.cos(poles.imag[:, None] * after + np.array([[0.3], [1.1]]))
    clean = 1e-5 * (q * (t >= 0)).T @ shapes
    x = clean * (1 + np.outer(np.minimum(after, 0.096) / 0.1, rng.normal(0, drift, clean.shape[1])))
    x += rng.normal(0, 1e-7, x.shape)
    fit = fit_decay(t, x, poles, t_min_s=1e-3)
    return t, poles, shapes, fit, noise_floor(t, x[:, :6], x[:, 6:], fit)


def test_a_pair_the_record_cannot_separate_is_flagged_and_a_longer_record_separates_it():
    """1.3 Hz apart in 96 ms: the fit reads each with 4.6x its gain alone, flagged though far above the floor, and its
    shapes take 5x the error a per-channel drift gives them in a record of 0.5 s; record_needed_s names the record
    that brings the gain to MAX_SEPARATION_GAIN, and there they are no longer flagged."""
    t, poles, shapes, fit, nf = _close_pair(0.096, np.random.default_rng(2))
    assert not nf.below.any() and nf.unseparated.all()
    assert np.all(nf.separation_gain > 4) and np.all(nf.separation_gain < 5), nf.separation_gain
    need = nf.record_needed_s
    assert np.all((need > 0.2) & (need < 0.26)), need           # about 1 / 4.3 Hz
    grid = np.arange(1e-3, 1e-3 + need[0] + 1 / 2500, 1 / 2500)
    assert np.all(separation_gains(grid, poles, 1e-3) <= MAX_SEPARATION_GAIN)
    assert np.any(separation_gains(grid[:-3], poles, 1e-3) > MAX_SEPARATION_GAIN)
    err_short = 1 - np.array([mac(fit.amplitudes[r:r + 1], shapes[r:r + 1])[0, 0] for r in range(2)])
    _, _, _, fit_long, nf_long = _close_pair(0.5, np.random.default_rng(2))
    assert not nf_long.unseparated.any() and np.all(np.isnan(nf_long.record_needed_s))
    err_long = 1 - np.array([mac(fit_long.amplitudes[r:r + 1], shapes[r:r + 1])[0, 0] for r in range(2)])
    assert np.all(err_short > 3 * err_long), (err_short, err_long)


def test_separated_modes_read_gain_one_and_a_pair_that_dies_out_first_needs_no_record_at_all():
    s = ModalStructure()
    wn = 2 * np.pi * np.asarray(s.freqs_hz)
    z = np.asarray(s.dampings)
    poles = -z * wn + 1j * wn * np.sqrt(1 - z ** 2)
    t = np.arange(-1, 246) / FPS                                  # the demo's record and poles
    assert np.all(np.abs(separation_gains(t, poles, T_MIN_S) - 1) < 0.02)
    assert np.all(np.isnan(record_needed_s(t, poles, T_MIN_S)))
    # 1 Hz apart at 5 % damping: gone within 0.1 s, before any record can tell them apart
    heavy = -0.05 * 2 * np.pi * np.array([40.0, 41.0]) + 2j * np.pi * np.array([40.0, 41.0])
    assert np.all(separation_gains(t, heavy, T_MIN_S) > MAX_SEPARATION_GAIN)
    assert np.all(np.isinf(record_needed_s(t, heavy, T_MIN_S)))


def test_the_note_names_the_pair_its_gain_and_the_record_that_would_separate_it():
    from odsplat.analysis.notes import ModesNotSeparated
    n = ModesNotSeparated((1, 2), (40.8, 42.1), (4.74, 4.74), (0.236, 0.236), 0.096, MAX_SEPARATION_GAIN)
    assert n.text.startswith("modes 1 (40.8 Hz), 2 (42.1 Hz): too close to one another for the video's 96 ms window "
                             "(the fit reads them with 4.7/4.7 x the gain each has alone, above 2)")
    assert "a video record of at least 236 ms separates them" in n.text
    never = ModesNotSeparated((1, 2), (40.0, 41.0), (9.0, 9.0), (np.inf, np.inf), 0.12, MAX_SEPARATION_GAIN)
    assert "dies out before any record separates them" in never.text


# ---------------------------------------------------------------------------------------------- the full structure

def test_the_full_field_floor_predicts_the_mac_of_a_shape_small_over_most_of_the_structure():
    """A mode whose shape is large on 10 of 200 points (where the sensors would be) and small elsewhere, read
    through the decay fit with white noise: full_field_expected_mac predicts the MAC of the fitted shape over all
    points against the true one (mean of 100 draws, within 0.02), far below what the large points alone allow; with
    the axes the direction floor drops (where this shape has no motion), it predicts the MAC of the shape less them:
    their noise goes."""
    rng = np.random.default_rng(3)
    f, z = np.array([60.0, 180.0]), np.array([0.01, 0.01])
    poles = -z * 2 * np.pi * f + 1j * 2 * np.pi * f * np.sqrt(1 - z ** 2)
    t = np.arange(-1, 240) / FPS
    after = np.clip(t, 0, None)
    q = np.exp(poles.real[:, None] * after) * np.cos(poles.imag[:, None] * after) * (t >= 0)     # (2, T)
    n = 200
    shapes = np.zeros((2, n, 3))
    shapes[:, :, 2] = rng.normal(size=(2, n)) * np.where(np.arange(n) < 10, 1.0, 0.08)          # z only
    sigma = 2e-5
    clean = 4e-5 * np.einsum("rt,rnc->tnc", q, shapes).reshape(len(t), -1)
    sd = design_gains(t, poles, T_MIN_S)
    predicted, measured, dropped, measured_dropped = [], [], [], []
    for _ in range(100):
        x = clean + rng.normal(0, sigma, clean.shape)
        fit = fit_decay(t, x, poles, t_min_s=T_MIN_S)
        a = fit.amplitudes.reshape(2, n, 3)
        predicted.append(full_field_expected_mac(a, np.full(n, sigma), sd))
        measured.append([mac(a[r].reshape(1, -1), shapes[r].reshape(1, -1))[0, 0] for r in range(2)])
        # the direction floor drops x and y, where the shape has no motion: their noise goes with them
        z_only = np.array([False, False, True])
        dropped.append(full_field_expected_mac(a, np.full(n, sigma), sd, kept=z_only))
        measured_dropped.append([mac((a[r] * z_only).reshape(1, -1), shapes[r].reshape(1, -1))[0, 0]
                                 for r in range(2)])
        # per axis: the same noise given per component reads the same
        assert np.allclose(full_field_expected_mac(a, np.full((n, 3), sigma), sd), predicted[-1])
    predicted, measured = np.mean(predicted, axis=0), np.mean(measured, axis=0)
    dropped, measured_dropped = np.mean(dropped, axis=0), np.mean(measured_dropped, axis=0)
    assert np.all(np.abs(predicted - measured) < 0.02), (predicted, measured)
    assert np.all(np.abs(dropped - measured_dropped) < 0.02) and np.all(dropped > predicted + 0.05), \
        (dropped, measured_dropped, predicted)
    assert 0.3 < measured.min() < 0.9                          # the test means something: the noise matters
    big = full_field_expected_mac(a[:, :10], np.full(10, sigma), sd)
    assert np.all(big > 0.95) and np.all(big > measured + 0.1), (big, measured)
    # a shape the direction floor left nothing of allows nothing (it read 1: no energy, and no noise either)
    nothing = full_field_expected_mac(a[:, :10], np.full(10, sigma), sd, kept=np.zeros(3, bool))
    assert np.all(nothing == 0.0), nothing
