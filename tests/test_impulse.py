"""Hammer pulses: the half-sine onset fit against known pulses and against five real hits."""
from __future__ import annotations

import math

import numpy as np
import pytest

from odsplat.spine.errors import InputError
from odsplat.spine.impulse import find_impacts, fit_pulse, half_sine
from odsplat.sync.align import _lag
from odsplat.sync.resample import fractional_shift


def test_onset_of_noisy_half_sines_to_a_hundredth_of_a_sample():
    rng = np.random.default_rng(1)
    fs = 25_600.0
    errors, threshold_errors = [], []
    for _ in range(100):
        onset = 200 + rng.uniform(0, 1)
        peak, tau = rng.uniform(30, 600), fs * rng.uniform(0.6e-3, 2e-3)
        f = half_sine(np.arange(600.0), onset, peak, tau) + 0.3 * rng.standard_normal(600)
        p = fit_pulse(f, fs)
        assert p.method == "half_sine" and p.residual < 0.01
        assert p.peak_n == pytest.approx(peak, rel=0.01) and p.duration_s == pytest.approx(tau / fs, rel=0.01)
        assert p.impulse_n_s == pytest.approx(2 * peak * tau / fs / np.pi, rel=0.01)
        errors.append(p.onset_sample - onset)
        threshold_errors.append(np.argmax(f > 10.0) - onset)  # the trigger's answer: first sample over 10 N
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert rms < 0.02, rms
    assert rms < 0.05 * float(np.sqrt(np.mean(np.square(threshold_errors))))


def test_fit_pulse_rejects_what_is_not_a_pulse():
    with pytest.raises(InputError, match="no positive force pulse"):
        fit_pulse(np.zeros(100), 1000.0)
    with pytest.raises(InputError, match="1-D force record"):
        fit_pulse(np.zeros((3, 3)), 1000.0)


def test_real_hits_lock_to_their_fitted_onsets(shared_data):
    """Five real hits on one point: once each response is locked to its fitted onset (to a fraction of a sample)
    and divided by its impulse, the responses line up to a fifth of a sample."""
    responses = []
    for k in range(1, 6):
        t, force, acc = np.load(shared_data / "pyfrf-hits" / f"measurements_{k}.npy")
        fs = 1.0 / (t[1] - t[0])
        assert len(find_impacts(force)) == 1
        p = fit_pulse(force, fs)
        assert p.method == "half_sine" and p.residual < 0.12  # real tips are not quite half sines
        assert 0.2e-3 < p.duration_s < 0.35e-3 and 60 < p.peak_n < 95
        i0 = int(math.floor(p.onset_sample)) - 10
        responses.append(fractional_shift(acc[i0:i0 + 1300, None], p.onset_sample % 1.0)[:1280] / p.impulse_n_s)
    for r in responses[1:]:
        lag, coeff = _lag(responses[0], r)
        assert abs(lag) < 0.3 and coeff > 0.97, (lag, coeff)


def test_every_stage_takes_the_same_onset():
    """Hit QC, the FRF's per-hit check, its segmentation of a long record and sync's timing all use
    odsplat.spine.impulse: on noisy half sines with a baseline offset, their onsets agree and match the truth."""
    from odsplat.analysis import check_frf_hit, split_hits
    from odsplat.spine.impulse import impact_onsets

    rng = np.random.default_rng(4)
    fs = 25_600.0
    for _ in range(20):
        onset = 300 + rng.uniform(0, 1)
        peak, tau = rng.uniform(50, 400), fs * rng.uniform(0.6e-3, 2e-3)
        base = rng.uniform(-2, 2)
        f = base + half_sine(np.arange(4000.0), onset, peak, tau) + 0.2 * rng.standard_normal(4000)
        frf = check_frf_hit(f, fs).onset_index
        qc = impact_onsets(f - base, fs)[0].onset_sample
        sync = fit_pulse(f - base, fs).onset_sample
        segments = split_hits(f, np.zeros((1, f.size)), fs, pretrigger_s=100 / fs, length_s=2000 / fs)
        cut = segments.start_index[0] + 100       # the segment starts `pretrigger_s` before the onset
        assert abs(frf - onset) < 0.1 and abs(qc - onset) < 0.1 and abs(sync - onset) < 0.1
        assert abs(frf - qc) < 0.05 and abs(frf - sync) < 0.05
        assert cut == round(frf)


def test_the_detector_measures_baseline_noise_and_each_impacts_extent():
    """On a 1.5 N offset with 0.2 N of noise and lost samples: the baseline and noise are the pretrigger's, each
    impact's onset and end are its half sine's, and a pulse under 10 noise sigmas is no impact however it stands
    out against the largest peak."""
    from odsplat.spine.impulse import ImpactDetector, ImpactSettings

    rng = np.random.default_rng(7)
    fs, tau = 25_600.0, 30.0
    t = np.arange(3000.0)
    f = 1.5 + half_sine(t, 400.3, 150.0, tau) + half_sine(t, 1200.6, 60.0, tau) + 0.2 * rng.standard_normal(t.size)
    f[2000:2032] = np.nan
    found = ImpactDetector().detect(f, fs)
    assert found.baseline_n == pytest.approx(1.5, abs=0.03) and found.noise_n == pytest.approx(0.2, rel=0.15)
    assert found.n == 2 and found.double_hit and found.main == 0
    assert [p.onset_sample for p in found.pulses] == pytest.approx([400.3, 1200.6], abs=0.05)
    assert found.end_indices == pytest.approx([400.3 + tau, 1200.6 + tau], abs=1.0)
    assert found.heights_n == pytest.approx([150.0, 60.0], rel=0.02)
    weak = 1.5 + half_sine(t, 400.3, 1.5, tau) + 0.2 * rng.standard_normal(t.size)   # 7.5 sigma
    assert ImpactDetector().detect(weak, fs).n == 0
    assert ImpactDetector(ImpactSettings(noise_sigmas=5.0)).detect(weak, fs).n == 1
    with pytest.raises(InputError, match="ImpactSettings.rebound_fraction"):
        ImpactSettings(rebound_fraction=1.0)
