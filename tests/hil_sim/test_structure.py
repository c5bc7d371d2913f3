"""The simulated structure: closed-form response, FRF against the modal sum, spectra, hammer options."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from odsplat.hil_sim.structure import Hammer, Impact, ModalStructure, _half_sine_response
from odsplat.spine.errors import InputError

TIP = (0.45, 0.0, 0.60)
SENSOR = (0.30, -0.03, 0.57)
SENSOR_DIR = (0.0, -1.0, 0.0)
HIT_DIR = tuple(np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, -0.5, -0.8]))


def test_half_sine_response_solves_the_ode():
    w, zeta, T = 2 * np.pi * 87.0, 0.015, 1.5e-3
    s = np.linspace(-0.002, 0.08, 3001)
    x, v, a = _half_sine_response(s, T, w, zeta)
    force = np.where((s >= 0) & (s <= T), np.sin(np.pi * np.clip(s, 0, T) / T), 0.0)
    assert np.abs(a + 2 * zeta * w * v + w * w * x - force).max() < 1e-9 * np.abs(a).max()
    on = s >= 0
    def rhs(t, y):
        return [y[1], (np.sin(np.pi * t / T) if t <= T else 0.0) - 2 * zeta * w * y[1] - w * w * y[0]]

    ref = solve_ivp(rhs, [0, s[-1]], [0, 0], t_eval=s[on], rtol=1e-10, atol=1e-15, max_step=2e-5)
    np.testing.assert_allclose(x[on], ref.y[0], atol=1e-8 * np.abs(x).max())
    np.testing.assert_allclose(v[on], ref.y[1], atol=1e-8 * np.abs(v).max())
    assert np.all(x[~on] == 0)


def test_modes_lie_in_the_specified_band_and_are_3d():
    st = ModalStructure()
    assert st.n_modes >= 4
    assert np.all((st.freqs_hz >= 10) & (st.freqs_hz <= 400))
    assert np.all((st.dampings >= 0.003) & (st.dampings <= 0.03))
    phi = st.mode_shapes(np.array([TIP]))[0]
    lateral = np.abs(phi[:, 1]) > 0.1 * np.abs(phi).max()
    vertical = np.abs(phi[:, 2]) > 0.1 * np.abs(phi).max()
    assert lateral.any() and vertical.any()
    # The base is bolted down: no motion there.
    assert np.abs(st.mode_shapes(np.array([[0.1, 0.1, 0.03]]))).max() == 0


def test_simulated_frf_equals_the_modal_sum():
    st = ModalStructure()
    fs, duration = 25_600.0, 16.0
    t = np.arange(int(fs * duration)) / fs
    imp = Impact(0.05, TIP, HIT_DIR, peak_n=150.0, duration_s=1.0e-3)
    acc = st.response(np.array([SENSOR]), [imp], t, kind="acceleration")[:, 0] @ np.array(SENSOR_DIR)
    freqs = np.fft.rfftfreq(t.size, 1 / fs)
    band = (freqs > 5) & (freqs < 450)
    # The force enters as a continuous half-sine, so divide by its exact spectrum.
    T, W = imp.duration_s, np.pi / imp.duration_s
    w = 2 * np.pi * freqs[band]
    force_spec = imp.peak_n * W * (1 + np.exp(-1j * w * T)) / (W**2 - w**2) * np.exp(-1j * w * imp.time_s)
    h_sim = np.fft.rfft(acc)[band] / fs / force_spec
    h_ref = st.frf(SENSOR, SENSOR_DIR, imp.point_m, HIT_DIR, freqs[band], kind="accelerance")
    err = np.abs(h_sim - h_ref) / np.abs(h_ref).max()
    assert err.max() < 2e-3, err.max()
    # Reciprocity: swapping input and output gives the same FRF.
    np.testing.assert_allclose(st.frf(TIP, HIT_DIR, SENSOR, SENSOR_DIR, freqs[band]),
                               st.frf(SENSOR, SENSOR_DIR, TIP, HIT_DIR, freqs[band]))


def test_every_mode_appears_in_the_accelerometer_spectra():
    st = ModalStructure()
    fs, duration = 10_240.0, 1.0  # 1 Hz resolution, as an impact test of 1 s gives
    t = np.arange(int(fs * duration)) / fs
    imp = Impact(0.01, TIP, HIT_DIR)
    sensors = np.array([SENSOR, TIP, (0.0, 0.045, 0.4)])
    acc = st.response(sensors, [imp], t, kind="acceleration")  # (T, 3 sensors, 3 axes)
    spec = np.abs(np.fft.rfft(acc.reshape(len(t), -1), axis=0)).sum(axis=1)
    freqs = np.fft.rfftfreq(len(t), 1 / fs)
    df = freqs[1]
    for f in st.freqs_hz:
        window = (freqs > 0.9 * f) & (freqs < 1.1 * f)
        peak = freqs[window][np.argmax(spec[window])]
        assert abs(peak - f) <= df, (f, peak)


def test_hammer_realism_options():
    hammer = Hammer(TIP, (0, 0, -2), peak_n=100.0, force_scatter=0.05, point_jitter_m=0.002, seed=3)
    assert np.isclose(np.linalg.norm(hammer.direction), 1.0)
    hits = [hammer.hit(1.0 * k) for k in range(200)]
    peaks = np.array([h[0].peak_n for h in hits])
    assert 0.04 < peaks.std() / peaks.mean() < 0.06
    points = np.array([h[0].point_m for h in hits])
    assert 0.0015 < points.std(axis=0).mean() < 0.0025
    double = hammer.hit(5.0, double=True)
    assert len(double) == 2 and double[1].time_s - double[0].time_s == pytest.approx(3e-3)
    t = np.arange(0, 0.01, 1e-5) + 5.0
    force = sum(i.force(t) for i in double)
    # Two separate pulses, the second weaker.
    assert force.max() == pytest.approx(double[0].peak_n) and np.sum(np.diff((force > 1).astype(int)) == 1) == 2
    with pytest.raises(InputError, match="duration_s"):
        Impact(0.0, TIP, (0, 0, 1), duration_s=5e-3)
