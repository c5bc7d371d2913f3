"""FRF from hammer hits: H1/H2/coherence against the simulated rig's analytic modal model, hit checks,
the exponential window's damping correction, and real LADISK recordings."""
from __future__ import annotations

import logging

import numpy as np
import pytest

from odsplat.analysis.frf import (
    FRFSettings,
    check_frf_hit,
    correct_damping,
    correct_poles,
    estimate_frf,
    exponential_window,
    force_window,
    split_hits,
)
from odsplat.hil_sim.structure import Impact, ModalStructure
from odsplat.spine.errors import InputError

FS = 5120.0
PULSE_S = 2e-3      # 10 samples a pulse: a 5-sample pulse's rectangle-rule spectrum is ~1 % off the continuous one
IN_POINT = (0.46, 0.03, 0.6)
OBLIQUE = tuple(np.array([1.0, 1.0, -1.0]) / np.sqrt(3))  # excites and sees all six modes
OUTPUTS = (((0.43, 0.0, 0.6), OBLIQUE), ((0.25, 0.03, 0.57), OBLIQUE))
S = ModalStructure()


def _record(impacts: list[Impact], t: np.ndarray, rng, force_noise: float, resp_noise: float):
    f = sum(i.force(t) for i in impacts)
    x = np.stack([S.response(np.array([p]), impacts, t, kind="acceleration")[:, 0] @ np.asarray(d)
                  for p, d in OUTPUTS])
    return f + force_noise * rng.standard_normal(f.shape), x + resp_noise * rng.standard_normal(x.shape)


def simulate(peaks_n, *, record_s=4.0, pre_s=0.05, force_noise=0.0, resp_noise=0.0, double=None, seed=0):
    """Hits of the given peaks (onsets at random sub-sample phases): force (H, n), responses (H, 2, n)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(record_s * FS)) / FS
    forces, responses = [], []
    for k, peak in enumerate(peaks_n):
        t_hit = pre_s + rng.uniform(0, 1) / FS
        impacts = [Impact(t_hit, IN_POINT, OBLIQUE, peak, PULSE_S)]
        if k == double:
            impacts.append(Impact(t_hit + 3e-3, IN_POINT, OBLIQUE, 0.4 * peak, PULSE_S))
        f, x = _record(impacts, t, rng, force_noise, resp_noise)
        forces.append(f)
        responses.append(x)
    return np.array(forces), np.array(responses)


def accelerance(freq_hz: np.ndarray, tau_s: float | None = None) -> np.ndarray:
    """Analytic accelerance (F, 2); with tau_s, that of the structure whose poles the exponential window
    moved by -1/tau_s: s^2 H(s) at s = i w + 1/tau_s, exactly what windowing force and response gives."""
    s = 2j * np.pi * np.asarray(freq_hz) + (0.0 if tau_s is None else 1.0 / tau_s)
    p_in = S.participation(IN_POINT, OBLIQUE)
    out = []
    for point, d in OUTPUTS:
        p_out = S.participation(point, d)
        h = sum(p_out[k] * p_in[k] / ((s + m.damping * m.omega) ** 2 + (m.omega * np.sqrt(1 - m.damping**2)) ** 2)
                for k, m in enumerate(S.modes))
        out.append(s**2 * h)
    return np.stack(out, axis=1)


def _lines(freq_hz: np.ndarray) -> np.ndarray:
    return np.array([np.argmin(np.abs(freq_hz - m.freq_hz)) for m in S.modes])


@pytest.fixture(scope="module")
def clean_hits():
    return simulate([150.0, 220.0, 300.0])


# ----------------------------------------------------------------------------------- windows

def test_windows_shape_and_tau():
    w = force_window(1000, 1000.0, onset_index=100.5, width_s=0.02, taper_s=0.01, lead_s=0.005)
    assert w[96] == 1.0 and w[120] == 1.0 and w[95] == 0.0 and w[131] == 0.0
    assert w[125] == pytest.approx(0.5 * (1 + np.cos(np.pi * 0.45)))  # 4.5 ms into the 10 ms taper
    e, tau = exponential_window(1001, 1000.0, start_index=200, end_value=0.01)
    assert tau == pytest.approx(0.8 / np.log(100.0))
    assert np.all(e[:201] == 1.0) and e[-1] == pytest.approx(0.01) and e[400] == pytest.approx(np.exp(-0.2 / tau))


def test_pole_and_damping_correction_signs():
    wn, z, tau = 2 * np.pi * 100.0, 0.02, 0.5
    measured = -(z * wn + 1 / tau) + 1j * wn * np.sqrt(1 - z**2)
    assert correct_poles(measured, tau) == pytest.approx(-z * wn + 1j * wn * np.sqrt(1 - z**2))
    zm = z + 1 / (tau * wn)
    assert correct_damping(100.0, zm, tau) == pytest.approx(z, rel=1e-3)


# ------------------------------------------------------------------------- against ground truth

def test_h1_matches_analytic_accelerance_at_every_resonance(clean_hits):
    force, resp = clean_hits
    rect = estimate_frf(force, resp, FS, FRFSettings(exponential_end=None), output_names=("tip", "mid"))
    i = _lines(rect.freq_hz)
    err = np.abs(rect.h1[i] / accelerance(rect.freq_hz[i]) - 1)
    assert err.max() < 0.01, err                 # measured: 0.1 to 0.4 %
    assert rect.exp_tau_s is None and rect.n_averages == 3 and rect.output_names == ("tip", "mid")

    win = estimate_frf(force, resp, FS)
    assert win.exp_tau_s == pytest.approx((4.0 - 0.05) / np.log(100), rel=1e-3)
    truth = accelerance(win.freq_hz[i], win.exp_tau_s)
    assert np.abs(win.h1[i] / truth - 1).max() < 0.01    # measured: 0.1 to 0.25 %
    # ... and the window really changed the peaks: the first mode's peak is ~45 % lower than undamped.
    assert abs(win.h1[i[0], 0]) < 0.7 * abs(accelerance(win.freq_hz[i[:1]])[0, 0])
    band = win.select(5.0, 450.0)
    assert np.median(band.coherence) > 0.999 and band.coherence[_lines(band.freq_hz)].min() > 0.9999
    assert np.abs(win.h2[i] / win.h1[i] - 1).max() < 1e-3
    # Force spectrum at 0 Hz: the rms over hits of a half sine's impulse 2 A T / pi.
    impulse = 2 * np.array([150.0, 220.0, 300.0]) * PULSE_S / np.pi
    assert win.force_spectrum[0] == pytest.approx(np.sqrt(np.mean(impulse**2)), rel=0.01)


def test_receptance_and_band(clean_hits):
    force, resp = clean_hits
    r = estimate_frf(force, resp, FS, FRFSettings(exponential_end=None, fmax_hz=500.0))
    assert r.freq_hz[-1] <= 500.0 and r.freq_hz[-1] > 499.0
    rec = r.to_receptance()
    i = _lines(rec.freq_hz)
    truth = np.stack([S.frf(p, d, IN_POINT, OBLIQUE, rec.freq_hz[i], kind="receptance") for p, d in OUTPUTS], 1)
    assert rec.output_unit == "m" and rec.h1[0, 0] == 0
    assert np.abs(rec.h("h1")[i] / truth - 1).max() < 0.01
    assert rec.to_receptance().h1 is rec.h1
    band = r.select(80.0, 90.0)
    assert band.freq_hz.min() >= 80.0 and band.freq_hz.max() <= 90.0 and band.h1.shape == (band.freq_hz.size, 2)
    with pytest.raises(InputError, match="output_unit"):
        estimate_frf(force, resp, FS, output_unit="g").to_receptance()
    with pytest.raises(InputError, match="estimator"):
        r.h("H3")


def test_exponential_window_damping_correction_recovers_modal_damping():
    force, resp = simulate([150.0, 220.0, 300.0], record_s=2.0)
    n = force.shape[1]
    r = estimate_frf(force, resp, FS, FRFSettings(n_fft=8 * n)).to_receptance()  # zero padding: 1/16 Hz lines
    for m in S.modes[:5]:  # the 371 Hz mode sits on the flank of the 262 Hz one: half power is biased there
        f_peak, zeta_windowed = _half_power(r.freq_hz, r.h1[:, 0], m.freq_hz)
        zeta = float(correct_damping(f_peak, zeta_windowed, r.exp_tau_s))
        assert zeta == pytest.approx(m.damping, rel=0.1), (m.freq_hz, zeta_windowed, zeta)
        if m.freq_hz < 100:  # where the window dominates, the uncorrected damping is far off
            assert zeta_windowed > 1.25 * m.damping


def _half_power(freq: np.ndarray, h: np.ndarray, f0: float) -> tuple[float, float]:
    band = (freq > 0.85 * f0) & (freq < 1.15 * f0)
    f, a = freq[band], np.abs(h[band]) ** 2
    k = int(np.argmax(a))
    half = a[k] / 2
    lo = k - int(np.argmax(a[k::-1] < half))
    hi = k + int(np.argmax(a[k:] < half))
    f1 = np.interp(half, [a[lo], a[lo + 1]], [f[lo], f[lo + 1]])
    f2 = np.interp(half, [a[hi], a[hi - 1]], [f[hi], f[hi - 1]])
    return float(f[k]), float((f2 - f1) / (2 * f[k]))


def test_output_noise_biases_h2_up_and_leaves_h1_unbiased():
    force, resp = simulate(np.linspace(150.0, 300.0, 10), resp_noise=20.0, force_noise=0.05, seed=2)
    r = estimate_frf(force, resp, FS)
    band = (r.freq_hz > 5) & (r.freq_hz < 450)
    ratio1 = np.abs(r.h1[band] / accelerance(r.freq_hz[band], r.exp_tau_s))
    ratio2 = np.abs(r.h2[band] / accelerance(r.freq_hz[band], r.exp_tau_s))
    assert np.median(r.coherence[band]) < 0.95                     # the noise matters (measured ~0.5-0.9)
    assert np.all(np.abs(r.h2) >= np.abs(r.h1) * (1 - 1e-12))       # |H2| / |H1| = 1 / coherence
    assert np.all(np.abs(np.median(ratio1, axis=0) - 1) < 0.03)     # measured: +0.7 %, +0.9 %
    assert np.all(np.median(ratio2, axis=0) > 1.1)                  # measured: +18 %, +100 %
    assert np.all(np.median(np.abs(ratio1 - 1), 0) < np.median(np.abs(ratio2 - 1), 0))


# ------------------------------------------------------------------------------- hit checks

def test_double_hit_is_rejected_and_the_rest_averaged(caplog):
    force, resp = simulate([150.0, 220.0, 300.0, 180.0], double=1, force_noise=0.05)
    check = check_frf_hit(force[1], FS)
    assert not check.accepted and check.n_impacts == 2
    assert check.reasons == ("double hit at +3.0 ms (40 % of the peak)",)
    with caplog.at_level(logging.WARNING):
        r = estimate_frf(force, resp, FS)
    assert "hit 1 rejected: double hit" in caplog.text
    assert r.n_averages == 3 and [h.accepted for h in r.hits] == [True, False, True, True]
    i = _lines(r.freq_hz)
    assert np.abs(r.h1[i] / accelerance(r.freq_hz[i], r.exp_tau_s) - 1).max() < 0.01
    clean = r.hits[0]
    assert clean.n_impacts == 1 and clean.peak_n == pytest.approx(150.0, rel=0.01)
    assert clean.pulse_width_s == pytest.approx(PULSE_S, rel=0.1)
    true_onset = 0.05 * FS + np.random.default_rng(0).uniform(0, 1)  # simulate's first draw with seed 0
    assert clean.onset_index == pytest.approx(true_onset, abs=0.2)  # measured: 0.01 sample off
    kept = estimate_frf(force, resp, FS, FRFSettings(reject_double_hits=False))
    assert kept.n_averages == 4 and kept.force_window_s > 3 * 5e-3  # the window spans both pulses


def test_overload_clipping_and_response_overload():
    force, resp = simulate([150.0, 220.0, 300.0])
    r = estimate_frf(force, resp, FS, FRFSettings(overload_n=250.0))
    assert r.n_averages == 2 and r.hits[2].reasons == ("overload: peak 297 N > 250 N",)  # the sampled peak
    clipped = np.minimum(force[1], 200.0)
    c = check_frf_hit(clipped, FS, full_scale_n=200.0)
    assert not c.accepted and c.reasons[0] == f"clipped: {int(np.sum(force[1] >= 200))} samples at full scale (200 N)"
    quiet_tip = resp[2] * np.array([[0.1], [1.0]])
    limit = 0.9 * np.abs(quiet_tip[1]).max()
    c = check_frf_hit(force[2], FS, responses=quiet_tip, response_full_scale=limit, output_names=("tip", "mid"))
    assert not c.accepted and len(c.reasons) == 1 and c.reasons[0].startswith("response overload: mid has")
    quiet = check_frf_hit(np.random.default_rng(0).standard_normal(2000), FS)
    assert not quiet.accepted and quiet.reasons[0].startswith("no impact")
    with pytest.raises(InputError, match="every hit was rejected: hit 0: overload"):
        estimate_frf(force, resp, FS, FRFSettings(overload_n=100.0))


def test_shape_and_value_errors_name_the_argument(clean_hits):
    force, resp = clean_hits
    cases = [
        (lambda: estimate_frf(force[None], resp, FS), "estimate_frf: force"),
        (lambda: estimate_frf(force, resp[:2], FS), "estimate_frf: responses"),
        (lambda: estimate_frf(force, resp[:, 0], FS), "estimate_frf: responses"),
        (lambda: estimate_frf(force, resp[..., :-1], FS), "estimate_frf: responses"),
        (lambda: estimate_frf(np.where(force > 290, np.nan, force), resp, FS), "estimate_frf: force"),
        (lambda: estimate_frf(force, resp, -FS), "estimate_frf: sample_rate_hz"),
        (lambda: estimate_frf(force, resp, FS, output_names=("a",)), "estimate_frf: output_names"),
        (lambda: estimate_frf(force, resp, FS, FRFSettings(n_fft=100)), "estimate_frf: settings.n_fft"),
        (lambda: estimate_frf(force, resp, FS, FRFSettings(fmax_hz=3000.0)), "estimate_frf: settings.fmax_hz"),
        (lambda: exponential_window(100, FS, end_value=1.5), "exponential_window: end_value"),
        (lambda: estimate_frf(force, resp, FS, FRFSettings(exponential_end=0.0)),
         "estimate_frf: settings.exponential_end"),
        (lambda: check_frf_hit(force, FS), "check_frf_hit: force"),
    ]
    for call, source in cases:
        with pytest.raises(InputError) as exc:
            call()
        assert exc.value.source == source
    one = estimate_frf(force[0], resp[0], FS)  # a single hit as (n,) and (n_out, n)
    assert one.n_averages == 1 and one.h1.shape[1] == 2


def test_split_hits_cuts_a_roving_record(caplog):
    """Four hits 4 s apart in one 14 s record: the second a double hit, the last too close to the end."""
    rng = np.random.default_rng(5)
    t = np.arange(int(14.0 * FS)) / FS
    onsets = np.array([0.3, 4.3, 8.3, 12.3]) + rng.uniform(0, 1, 4) / FS
    impacts = [Impact(t0, IN_POINT, OBLIQUE, p, PULSE_S) for t0, p in zip(onsets, (150.0, 250.0, 200.0, 180.0))]
    impacts.append(Impact(onsets[1] + 3e-3, IN_POINT, OBLIQUE, 100.0, PULSE_S))
    force, resp = _record(impacts, t, rng, force_noise=0.05, resp_noise=0.01)
    with caplog.at_level(logging.WARNING):
        seg = split_hits(force, resp, FS, pretrigger_s=0.05, length_s=3.9)
    assert "skipped the hit at 12.3" in caplog.text
    assert seg.force.shape == (3, int(3.9 * FS)) and seg.responses.shape == (3, 2, int(3.9 * FS))
    assert np.abs(seg.start_index - (onsets[:3] * FS - 0.05 * FS)).max() < 1.5
    r = estimate_frf(seg.force, seg.responses, FS)
    assert [h.accepted for h in r.hits] == [True, False, True]
    i = _lines(r.freq_hz)
    assert np.abs(r.h1[i] / accelerance(r.freq_hz[i], r.exp_tau_s) - 1).max() < 0.01
    with pytest.raises(InputError, match="no impact"):
        split_hits(np.zeros(1000), np.zeros(1000), FS, 0.01, 0.1)


# ------------------------------------------------------------------------------- real recordings

def _peak_near(freq: np.ndarray, mag: np.ndarray, f0: float) -> float:
    """The line of the largest |H| within +-10 % of f0."""
    band = (freq > 0.9 * f0) & (freq < 1.1 * f0)
    return float(freq[band][np.argmax(mag[band])])


def test_pyfrf_five_real_hits(shared_data):
    data = np.stack([np.load(shared_data / "pyfrf-hits" / f"measurements_{k}.npy") for k in range(1, 6)])
    fs = round(1.0 / float(np.mean(np.diff(data[0, 0]))))
    assert fs == 25600
    r = estimate_frf(data[:, 1], data[:, 2][:, None], fs, output_names=("acc",))
    assert r.n_averages == 5 and all(h.n_impacts == 1 for h in r.hits)
    assert all(68 <= h.peak_n <= 89 for h in r.hits)
    assert np.median(r.select(100.0, 5000.0).coherence) > 0.99   # measured: 0.9999
    mag = np.abs(r.h1[:, 0])
    for f0 in (900.0, 3669.0, 4128.0, 5969.0):
        assert _peak_near(r.freq_hz, mag, f0) == pytest.approx(f0, rel=0.01)


def test_ladisk_beam_one_hit(shared_data):
    from odsplat.spine.io.signals import read_signals

    sig = read_signals(shared_data / "ladisk-imaging-tutorial" / "acceleration.lvm")
    acc = next(c for c in sig.channels if c.unit == "m/s^2").values
    force = next(c for c in sig.channels if c.unit == "N").values
    seg = split_hits(force, acc, sig.sample_rate_hz, pretrigger_s=0.5e-3, length_s=0.99)
    assert seg.force.shape[0] == 1 and seg.start_index[0] < 30
    r = estimate_frf(seg.force, seg.responses, sig.sample_rate_hz)
    assert r.hits[0].accepted and r.hits[0].peak_n == pytest.approx(195.4, rel=0.01)
    mag = np.abs(r.h1[:, 0])
    for f0 in (695.8, 1898.0, 3671.2):
        assert _peak_near(r.freq_hz, mag, f0) == pytest.approx(f0, rel=0.01)
