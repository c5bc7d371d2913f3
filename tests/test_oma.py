"""Output-only modal analysis (analysis/oma.py) against ground truth: a 3-mode system driven by white noise and in
free decay, simulated exactly (each mode's zero-order-hold discretisation, so the sampled response has exactly the
continuous poles), scipy's cross-spectra, a sine of known amplitude and phase, white noise of known level, the
LADISK beam's video (its accelerometer's modes) and pyOMA2's SSI-cov on the same data."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import csd, lfilter

from odsplat.analysis.correlation import mac
from odsplat.analysis.ema import StabilisationChart
from odsplat.analysis.oma import fdd, identify, noise_psd, ods_at, ssi_cov
from odsplat.analysis.plots import plot_stabilisation
from odsplat.spine.errors import InputError

from .conftest import load_bench

# the 3-mode system of bench/oma.py (12 channels on a pinned beam's first three bending shapes)
_SYSTEM = load_bench("oma")
FS_HZ, FREQ_HZ, DAMPING, N_CH = _SYSTEM.FS_HZ, _SYSTEM.FREQ_HZ, _SYSTEM.DAMPING, _SYSTEM.N_CH
_true_shapes, _modal_response = _SYSTEM.true_shapes, _SYSTEM.modal_response
BAND = {"fmin_hz": 10.0, "fmax_hz": 200.0}

# ../shared/data/README.md: the accelerometer's modes of the LADISK beam (sdypy-EMA LSCF), and the weak one at
# 2777.6 Hz (0.24 %) that tests/analysis/test_ladisk.py's fit finds beside them
LADISK_HZ = np.array([695.8, 1898.0, 2777.6])
LADISK_DAMPING = np.array([0.0047, 0.0031, 0.0024])
LADISK_UNSEEN_HZ = 3671.2          # in the accelerometer, not in the camera's spectrum
LADISK_FPS = 15000.0




def _noise_sigma(scale: float) -> np.ndarray:
    return scale * np.linspace(1.0, 2.0, N_CH)          # a different white-noise level per channel


@pytest.fixture(scope="module")
def ambient() -> tuple[np.ndarray, np.ndarray]:
    """120 s of response to white modal forces (scaled so that the modes' displacements are alike), plus white
    measurement noise about 5 % of the response's RMS; and the noise's true PSD per channel (unit^2/Hz)."""
    rng = np.random.default_rng(1)
    gain = np.sqrt(DAMPING * (FREQ_HZ / FREQ_HZ[0]) ** 3)
    y = _modal_response(rng.standard_normal((int(120 * FS_HZ), 3)) * gain)
    sigma = _noise_sigma(0.035 * y.std())
    return y + sigma * rng.standard_normal(y.shape), 2 * sigma**2 / FS_HZ


@pytest.fixture(scope="module")
def decay() -> tuple[np.ndarray, np.ndarray]:
    """3 s of free decay after an impulse on every mode, plus white noise of 1-2 % of the peak."""
    rng = np.random.default_rng(2)
    impulse = np.zeros((int(3 * FS_HZ), 3))
    impulse[0] = FREQ_HZ                                 # modal velocities alike in displacement
    y = _modal_response(impulse)
    sigma = _noise_sigma(0.01 * np.abs(y).max())
    return y + sigma * rng.standard_normal(y.shape), 2 * sigma**2 / FS_HZ


@pytest.fixture(scope="module")
def ambient_result(ambient):
    return identify(ambient[0], FS_HZ, **BAND)


def _assert_modes_match_truth(result, *, freq_rel: float = 0.005, damping_rel: float = 0.3, min_mac: float = 0.99):
    assert result.freq_hz.size == 3, result.freq_hz
    assert np.all(np.abs(result.freq_hz / FREQ_HZ - 1) < freq_rel), result.freq_hz
    assert np.all(np.abs(result.damping / DAMPING - 1) < damping_rel), result.damping
    assert np.all(np.diag(mac(result.shapes, _true_shapes())) >= min_mac), mac(result.shapes, _true_shapes())
    assert np.allclose(np.abs(result.shapes).max(axis=1), 1.0)
    assert np.all(result.mpc > 0.99)                     # the true modes are real


# ------------------------------------------------------------------ FDD, ODS, noise

@pytest.mark.parametrize("n_ch, seconds", [(3, 20.0), (12, 0.6)])   # more segments than channels; fewer
def test_fdd_is_the_svd_of_scipys_cross_spectral_matrix(n_ch, seconds):
    rng = np.random.default_rng(3)
    x = lfilter([1.0], [1.0, -0.9], rng.standard_normal((int(seconds * FS_HZ), n_ch)) @ rng.standard_normal(
        (n_ch, n_ch)), axis=0)
    res = fdd(x, FS_HZ, nperseg=64)
    f, _ = csd(x[:, 0], x[:, 0], FS_HZ, nperseg=64)
    # ours: G[i, j] = sum X_i conj(X_j); scipy's csd(a, b) sums conj(A) B, so G[i, j] = csd(x_j, x_i)
    g = np.stack([np.stack([csd(x[:, j], x[:, i], FS_HZ, nperseg=64)[1] for j in range(n_ch)], axis=1)
                  for i in range(n_ch)], axis=1)
    ev, vec = np.linalg.eigh(g)
    k = res.singular_values.shape[1]
    assert np.allclose(res.freqs_hz, f) and res.nperseg == 64 and k == min(4, n_ch, res.n_segments)
    assert np.allclose(res.singular_values, ev[:, ::-1][:, :k], rtol=1e-9, atol=1e-12 * ev.max())
    top = vec[:, :, -1]
    assert np.allclose(np.abs(np.sum(top.conj() * res.first_vectors, axis=1)), 1.0, atol=1e-8)
    assert np.allclose(np.linalg.norm(res.first_vectors, axis=1), 1.0)


def test_ods_at_gives_a_sines_amplitudes_and_phases():
    n, nperseg = 20000, 1000
    t = np.arange(n) / FS_HZ
    f0 = 50 * FS_HZ / nperseg                            # on a line: 25 Hz
    amp, phase = np.array([1.0, 0.5, 2.0]), np.array([0.0, 0.4, -1.2])
    x = amp * np.sin(2 * np.pi * f0 * t[:, None] - phase) + 1e-4 * np.random.default_rng(4).standard_normal((n, 3))
    ods = ods_at(x, FS_HZ, f0 + 0.1, nperseg=nperseg)    # the nearest line
    # Hann: a sine on a line puts its power A^2 / 2 into 1.5 lines' worth of density
    assert np.allclose(np.abs(ods), amp / np.sqrt(2 * 1.5 * FS_HZ / nperseg), rtol=1e-3)
    assert np.allclose(np.angle(ods / ods[0]), -(phase - phase[0]), atol=1e-3)
    assert np.argmax(np.abs(ods)) == 2 and ods[2].imag == 0 and ods[2].real > 0


def test_noise_psd_of_white_noise_is_its_level():
    sigma = _noise_sigma(0.3)
    x = sigma * np.random.default_rng(5).standard_normal((60000, N_CH))
    level = noise_psd(x, FS_HZ, exclude_hz=[100.0])
    assert np.allclose(level / (2 * sigma**2 / FS_HZ), 1.0, atol=0.05)


# ------------------------------------------------------------------ SSI and identification

def test_ssi_cov_finds_the_exact_poles_of_a_noise_free_decay():
    impulse = np.zeros((1500, 3))
    impulse[0] = FREQ_HZ
    levels = ssi_cov(_modal_response(impulse), FS_HZ, max_order=6)
    assert [lv.order for lv in levels] == [2, 4, 6]
    top = levels[-1]
    assert np.allclose(top.freq_hz, FREQ_HZ, rtol=1e-7)
    assert np.allclose(top.damping, DAMPING, rtol=1e-4)
    assert np.all(np.diag(mac(top.participation, _true_shapes())) > 1 - 1e-9)   # the shapes ride along


def test_identify_ambient_response(ambient, ambient_result):
    x, true_noise = ambient
    res = ambient_result
    _assert_modes_match_truth(res)          # measured: 30.994, 76.887, 139.900 Hz; 1.10, 1.48, 1.86 %
    assert isinstance(res.chart, StabilisationChart) and res.chart.orders == tuple(range(2, 61, 2))
    assert all(m.n_stable >= 12 for m in res.modes) and res.harmonics == ()
    assert np.all([2.5 < m.kurtosis < 3.5 for m in res.modes])       # Gaussian: randomly excited
    assert np.all([m.snr > 100 for m in res.modes])
    # Between and above the modes their skirts add to the noise: an upper bound (measured 1.1-3.2; 3.35 at worst
    # over 8 seeds)
    assert np.all((res.noise_psd > 0.9 * true_noise) & (res.noise_psd < 4 * true_noise)), res.noise_psd / true_noise
    fig = plot_stabilisation(res.chart, band_hz=res.band_hz, selected_hz=res.freq_hz)
    assert len(fig.axes) == 1
    # the ODS at a mode is its shape
    assert mac(ods_at(x, FS_HZ, 77.0), _true_shapes()[1])[0, 0] > 0.99


def test_identify_free_decay(decay):
    x, true_noise = decay
    res = identify(x, FS_HZ, **BAND)
    _assert_modes_match_truth(res)          # measured: 30.998, 76.998, 140.048 Hz; 1.00, 1.49, 1.92 %
    assert np.all([m.kurtosis > 5 for m in res.modes])               # a decay: heavy tails
    # The response dies away: what is left of the band is the noise (measured 0.94-1.10; 0.81-1.16 over 8 seeds)
    assert np.allclose(res.noise_psd / true_noise, 1.0, atol=0.25), res.noise_psd / true_noise


def test_a_steady_sine_is_no_mode(ambient):
    x = ambient[0][: int(60 * FS_HZ)]
    t = np.arange(x.shape[0]) / FS_HZ
    hum = 0.3 * x.std() * np.sin(2 * np.pi * 110.0 * t)[:, None] * np.linspace(1, -1, N_CH)
    res = identify(x + hum, FS_HZ, max_order=40, **BAND)
    # Its poles' damping (about 1e-5) wanders too much from order to order to be stable: no mode, the rest intact
    _assert_modes_match_truth(res)
    # Asked for, it is given, flagged: its modal coordinate is a sine's (kurtosis 1.5), not a random response's
    hum_mode, mode = identify(x + hum, FS_HZ, approx_freq_hz=[110.0, 77.0], max_order=40, **BAND).modes
    assert hum_mode.freq_hz == pytest.approx(110.0, rel=1e-4) and hum_mode.damping < 1e-3
    assert hum_mode.harmonic and hum_mode.kurtosis < 1.7 and not mode.harmonic


def test_identify_at_given_frequencies_and_the_strongest_modes(ambient, ambient_result):
    x = ambient[0][: int(60 * FS_HZ)]
    manual = identify(x, FS_HZ, approx_freq_hz=[77.5], max_order=30, **BAND)
    assert manual.freq_hz == pytest.approx([77.0], rel=0.005)
    assert mac(manual.shapes, _true_shapes()[1])[0, 0] > 0.99
    # the first mode's displacement spectrum peaks highest (its response has the same RMS in a narrower band)
    assert np.argmax([m.peak_psd for m in ambient_result.modes]) == 0
    assert identify(x, FS_HZ, n_modes=1, max_order=30, **BAND).freq_hz == pytest.approx([31.0], rel=0.005)
    refs = identify(x, FS_HZ, ref_channels=[0, 5, 9], max_order=30, **BAND)
    _assert_modes_match_truth(refs)


def test_identify_is_deterministic(decay):
    a, b = (identify(decay[0].copy(), FS_HZ, **BAND) for _ in range(2))
    for get in (lambda r: r.freq_hz, lambda r: r.damping, lambda r: r.shapes, lambda r: r.noise_psd,
                lambda r: r.fdd.singular_values, lambda r: r.fdd.first_vectors, lambda r: r.chart.flat()[1]):
        assert np.array_equal(get(a), get(b))


@pytest.mark.parametrize("call, source, words", [
    (lambda x: identify(np.where(np.arange(x.shape[1]) == 3, np.nan, x), FS_HZ), "oma.x", "channels [3]"),
    (lambda x: fdd(x, 0.0), "oma.fs_hz", "positive"),
    (lambda x: fdd(x, float("nan")), "oma.fs_hz", "finite"),
    (lambda x: noise_psd(x, "fast"), "oma.fs_hz", "sample rate"),
    (lambda x: ssi_cov(x[:40], FS_HZ, max_order=4), "oma.x", "at least 64 samples"),
    (lambda x: ssi_cov(x[:150], FS_HZ, max_order=8), "oma.x", "block rows"),
    (lambda x: identify(x, FS_HZ, fmin_hz=300.0), "oma.fmin_hz, fmax_hz", "fs_hz / 2"),
    (lambda x: ssi_cov(x, FS_HZ, max_order=8, ref_channels=[0, 0]), "oma.ref_channels", "distinct"),
    (lambda x: ssi_cov(x, FS_HZ, max_order=40, n_lags=3), "oma.n_lags", "max_order"),
    (lambda x: fdd(x, FS_HZ, nperseg=10**6), "oma.nperseg", "segment length"),
    (lambda x: fdd(x[:, :, None], FS_HZ), "oma.x", "(samples, channels)"),
    (lambda x: ods_at(x, FS_HZ, 400.0), "oma.freq_hz", "Nyquist"),
])
def test_bad_input_is_refused_in_one_line(decay, call, source, words):
    with pytest.raises(InputError) as err:
        call(decay[0][:1000])
    assert err.value.source == source and words in err.value.problem and "\n" not in str(err.value)


# ------------------------------------------------------------------ the LADISK beam's video

@pytest.fixture(scope="module")
def ladisk_video(shared_data) -> np.ndarray:
    path = shared_data / "ladisk-imaging-tutorial" / "displacements_lk.npy"
    if not path.is_file():
        pytest.skip(f"the LADISK video displacements are not at {path}")
    disp = np.load(path)
    assert disp.shape == (15, 3750, 2)
    return disp


def test_ladisk_video_modes_match_the_accelerometers(ladisk_video):
    # Image axis 0 is the beam's bending (tests/analysis/test_ladisk.py); axis 1 holds tracking noise and drift.
    x = ladisk_video[:, :, 0].T
    res = identify(x, LADISK_FPS, fmin_hz=100.0, fmax_hz=5000.0)
    # measured: 695.56, 1898.09, 2775.17 Hz; 0.479, 0.300, 0.229 %
    assert res.freq_hz.size == 3, res.freq_hz
    assert np.all(np.abs(res.freq_hz / LADISK_HZ - 1) < 0.005), res.freq_hz
    assert np.all(np.abs(res.damping / LADISK_DAMPING - 1) < 0.3), res.damping
    assert not np.any(np.abs(res.freq_hz / LADISK_UNSEEN_HZ - 1) < 0.05)
    # A steady 2466 Hz sine in the video (no decay over the record; not in the accelerometer) is left out
    assert [round(m.freq_hz) for m in res.harmonics] == [2466]
    assert res.modes[0].snr > 1000 and res.modes[1].snr > 100 and np.all(res.mpc[:2] > 0.99)
    # The first bending mode of a free-free beam: two nodes, ends in phase, middle against them
    first = res.shapes[0].real
    assert np.count_nonzero(np.diff(np.sign(first)) != 0) == 2 and first[0] > 0.9 and first[-1] > 0.2
    assert mac(ods_at(x, LADISK_FPS, res.freq_hz[0]), res.shapes[0])[0, 0] > 0.99
    noise_axis = identify(ladisk_video[:, :, 1].T, LADISK_FPS, fmin_hz=100.0, fmax_hz=5000.0, n_lags=25)
    assert noise_axis.modes == () and noise_axis.fdd.peaks_hz(100.0, 5000.0).size <= 1


# ------------------------------------------------------------------ pyOMA2's SSI-cov on the same data

def test_pyoma2_ssicov_agrees(decay):
    pytest.importorskip("pyoma2")
    from pyoma2.algorithms import SSI
    from pyoma2.setup import SingleSetup

    x = decay[0]
    setup = SingleSetup(x, fs=FS_HZ)
    theirs = SSI(name="SSIcov", method="cov", br=20, ordmax=30)
    setup.add_algorithms(theirs)
    setup.run_all()
    setup.mpe("SSIcov", sel_freq=list(FREQ_HZ), order_in=30)
    ours = identify(x, FS_HZ, **BAND)
    assert np.allclose(theirs.result.Fn, FREQ_HZ, rtol=0.005), theirs.result.Fn
    assert np.allclose(ours.freq_hz, theirs.result.Fn, rtol=0.002), (ours.freq_hz, theirs.result.Fn)
    assert np.allclose(ours.damping, theirs.result.Xi, rtol=0.3), (ours.damping, theirs.result.Xi)
    assert np.all(np.diag(mac(ours.shapes, theirs.result.Phi.T)) > 0.99)
