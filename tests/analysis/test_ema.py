"""LSCF + LSFD against the analytic FRFs of the simulated structure, pole selection, and the input checks."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from odsplat.analysis.ema import (
    LSFDResult,
    PolesAtOrder,
    fit_modes,
    lscf,
    lsfd,
    pole_damping,
    pole_freq_hz,
    pole_from_freq_damping,
    select_poles,
    stabilisation,
)
from odsplat.hil_sim.structure import ModalStructure
from odsplat.spine.errors import InputError

STRUCTURE = ModalStructure()
FREQ_HZ = np.arange(2001) * 0.25  # 0-500 Hz
BAND_HZ = (5.0, 480.0)
NOISE = 1e-3  # complex noise, relative to each FRF's peak


def _unit(*v) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


# Hits on the arm's top, obliquely, so that every mode is excited: at the tip corner and mid-arm.
INPUTS = [((0.46, 0.03, 0.60), _unit(1, 1, -1)), ((0.30, -0.03, 0.60), _unit(0, -1, -1))]
OUTPUTS = [((0.43, 0.0, 0.60), _unit(0, 0, 1)), ((0.43, 0.03, 0.57), _unit(0, 1, 0)),
           ((0.045, 0.0, 0.40), _unit(1, 0, 0)), ((0.0, 0.045, 0.50), _unit(0, 1, 0)),
           ((0.25, 0.03, 0.60), _unit(0, 0, 1))]


def _frfs(kind: str, *, inputs=INPUTS[:1], noise: float = NOISE, seed: int = 0,
          structure: ModalStructure = STRUCTURE) -> np.ndarray:
    """(F, n_out, n_in) analytic FRFs plus complex noise of `noise` times each FRF's peak."""
    h = np.stack([np.stack([structure.frf(po, do, pi, di, FREQ_HZ, kind=kind) for pi, di in inputs], axis=-1)
                  for po, do in OUTPUTS], axis=1)
    rng = np.random.default_rng(seed)
    scale = noise * np.abs(h).max(axis=0) / np.sqrt(2)
    return h + scale * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape))


def _true_residues(inputs=INPUTS[:1]) -> np.ndarray:
    """A_r = phi_out phi_in / (2 i w_d): (n_modes, n_out, n_in)."""
    phi_out = np.stack([STRUCTURE.participation(p, d) for p, d in OUTPUTS], axis=1)  # (n_modes, n_out)
    phi_in = np.stack([STRUCTURE.participation(p, d) for p, d in inputs], axis=1)
    wd = 2 * np.pi * STRUCTURE.freqs_hz * np.sqrt(1 - STRUCTURE.dampings**2)
    return phi_out[:, :, None] * phi_in[:, None, :] / (2j * wd)[:, None, None]


def _true_poles(structure: ModalStructure = STRUCTURE) -> np.ndarray:
    return pole_from_freq_damping(structure.freqs_hz, structure.dampings)


def _mac(a, b) -> float:
    a, b = np.ravel(a), np.ravel(b)
    return float(np.abs(np.vdot(a, b)) ** 2 / (np.vdot(a, a).real * np.vdot(b, b).real))


@pytest.fixture(scope="module")
def accelerance_fit():
    return fit_modes(FREQ_HZ, _frfs("accelerance")[:, :, 0], frf_kind="accelerance", fmin_hz=BAND_HZ[0],
                     fmax_hz=BAND_HZ[1], max_order=80, output_names=[f"p{i}" for i in range(len(OUTPUTS))])


def test_fit_modes_finds_the_six_modes(accelerance_fit):
    fit = accelerance_fit
    assert fit.n_modes == 6, fit.freq_hz
    assert np.all(np.diff(fit.freq_hz) > 0)
    assert np.max(np.abs(fit.freq_hz / STRUCTURE.freqs_hz - 1)) < 0.002
    assert np.max(np.abs(fit.damping / STRUCTURE.dampings - 1)) < 0.10
    assert np.allclose(fit.poles_rad_s, pole_from_freq_damping(fit.freq_hz, fit.damping))
    truth = _true_residues()[:, :, 0]
    assert fit.shapes.shape == (6, len(OUTPUTS)) and fit.residues.shape == (6, len(OUTPUTS))
    assert min(_mac(fit.shapes[r], truth[r]) for r in range(6)) > 0.99
    # The residues are displacement residues, scaled: within 3 % of the analytic ones (norm-relative).
    err = np.linalg.norm(fit.shapes - truth, axis=1) / np.linalg.norm(truth, axis=1)
    assert np.max(err) < 0.03, err
    assert np.all(fit.lsfd.fit_error < 0.05)
    assert fit.band_hz == BAND_HZ and fit.output_names == ("p0", "p1", "p2", "p3", "p4")
    # Real shapes: each mode is (nearly) real for this proportionally damped structure.
    real = fit.lsfd.normal_mode_shapes()
    assert min(_mac(real[r], truth[r]) for r in range(6)) > 0.99


@pytest.mark.parametrize("kind", ["receptance", "mobility", "accelerance"])
def test_lsfd_gives_displacement_residues_in_every_kind(kind):
    h = _frfs(kind, noise=0.0)[:, :, 0]
    fit = lsfd(FREQ_HZ, h, _true_poles(), frf_kind=kind, fmin_hz=5.0)
    truth = _true_residues()[:, :, 0]
    assert fit.residues.shape == truth.shape
    assert np.abs(fit.residues - truth).max() < 1e-6 * np.abs(truth).max()
    band = FREQ_HZ >= 5
    assert np.abs(fit.synthesize(FREQ_HZ[band]) - h[band]).max() < 1e-6 * np.abs(h).max()


def test_residual_terms_absorb_the_modes_outside_the_band():
    h = _frfs("accelerance", noise=0.0)[:, :, 0]
    inside = slice(3, 5)  # 142 and 262 Hz in a 100-300 Hz band; 23.5, 31, 86 and 371 Hz lie outside
    with_res = lsfd(FREQ_HZ, h, _true_poles()[inside], frf_kind="accelerance", fmin_hz=100, fmax_hz=300)
    without = lsfd(FREQ_HZ, h, _true_poles()[inside], frf_kind="accelerance", fmin_hz=100, fmax_hz=300,
                   residuals=False)
    truth = _true_residues()[inside, :, 0]
    err = np.linalg.norm(with_res.residues - truth) / np.linalg.norm(truth)
    err_without = np.linalg.norm(without.residues - truth) / np.linalg.norm(truth)
    assert err < 0.01 and err_without > 5 * err, (err, err_without)
    assert np.mean(with_res.fit_error) < np.mean(without.fit_error) / 3
    assert np.all(without.lower_residual == 0) and np.all(with_res.lower_residual != 0)
    assert np.all(with_res.upper_residual != 0)


def test_multiple_references():
    inputs = INPUTS[:2]
    h = _frfs("mobility", inputs=inputs, noise=3e-4, seed=1)
    fit = fit_modes(FREQ_HZ, h, frf_kind="mobility", fmin_hz=BAND_HZ[0], fmax_hz=BAND_HZ[1], max_order=40)
    assert fit.n_modes == 6, fit.freq_hz
    assert np.max(np.abs(fit.freq_hz / STRUCTURE.freqs_hz - 1)) < 0.002
    assert np.max(np.abs(fit.damping / STRUCTURE.dampings - 1)) < 0.10
    truth = _true_residues(inputs)
    assert fit.residues.shape == (6, len(OUTPUTS), 2) and fit.shapes.shape == (6, len(OUTPUTS))
    assert min(_mac(fit.residues[r, :, i], truth[r, :, i]) for r in range(6) for i in range(2)) > 0.99
    # LSCF's participation vectors at the top order are the input-side mode shapes.
    top = fit.chart.levels[-1]
    phi_in = np.stack([STRUCTURE.participation(p, d) for p, d in inputs], axis=1)
    for r, f0 in enumerate(STRUCTURE.freqs_hz):
        k = np.argmin(np.abs(top.freq_hz - f0))
        assert _mac(top.participation[k], phi_in[r]) > 0.999


def test_exponential_window_damping_is_removed():
    tau_s = 0.5
    # exp(-t / tau) on the impulse response moves every pole by -1 / tau and keeps the residues.
    shifted = _true_poles() - 1 / tau_s
    windowed = ModalStructure(modes=tuple(
        dataclasses.replace(m, freq_hz=float(pole_freq_hz(p)), damping=float(pole_damping(p)))
        for m, p in zip(STRUCTURE.modes, shifted)))
    h = _frfs("mobility", structure=windowed)[:, :, 0]
    fit = fit_modes(FREQ_HZ, h, frf_kind="mobility", fmin_hz=BAND_HZ[0], fmax_hz=BAND_HZ[1], max_order=80)
    assert fit.n_modes == 6, fit.freq_hz
    added = 1 / (tau_s * 2 * np.pi * STRUCTURE.freqs_hz)  # 1.35 % at 23.5 Hz, 0.09 % at 371 Hz
    assert np.max(np.abs(fit.damping / windowed.dampings - 1)) < 0.10
    assert np.all(fit.damping - STRUCTURE.dampings > 0.5 * added)
    true = fit.with_corrected_damping(tau_s)
    assert np.max(np.abs(true.damping / STRUCTURE.dampings - 1)) < 0.10
    assert np.max(np.abs(true.freq_hz / STRUCTURE.freqs_hz - 1)) < 0.002
    assert true.shapes is fit.shapes and true.chart is fit.chart
    with pytest.raises(InputError, match="tau_s"):
        fit.with_corrected_damping(0.01)  # would leave the modes undamped


def test_manual_selection_picks_the_poles_near_given_frequencies(accelerance_fit):
    chart = accelerance_fit.chart
    poles = select_poles(chart, approx_freq_hz=[87.0, 260.0])
    assert np.max(np.abs(pole_freq_hz(poles) / STRUCTURE.freqs_hz[[2, 4]] - 1)) < 0.002
    order, all_poles, status = chart.flat()
    assert set(status[np.isin(all_poles, poles)]) == {"stable"}
    with pytest.raises(InputError, match="approx_freq_hz"):
        select_poles(chart, approx_freq_hz=[600.0])


def test_stabilisation_statuses():
    def level(order, freqs, dampings, part=None):
        return PolesAtOrder(order, pole_from_freq_damping(freqs, dampings), part)

    chart = stabilisation([level(2, [100.0], [0.01]),
                           level(3, [100.5, 200.0], [0.0102, 0.02]),
                           level(4, [100.4, 150.0, 201.0], [0.015, 0.01, 0.02])])
    assert chart.orders == (2, 3, 4)
    assert [list(s) for s in chart.status] == [["new"], ["stable", "new"], ["freq", "new", "stable"]]
    v1, v2 = np.array([[1.0, 0.0]]), np.array([[0.0, 1.0]])
    vec = stabilisation([level(2, [100.0], [0.01], v1), level(3, [100.0], [0.01], v2), level(4, [100.0], [0.01], v2)])
    assert [list(s) for s in vec.status] == [["new"], ["damping"], ["stable"]]


def test_lscf_returns_only_physical_poles_in_the_band():
    levels = lscf(FREQ_HZ, _frfs("accelerance", noise=0.0)[:, :, 0], max_order=20, fmin_hz=50, fmax_hz=300,
                  orders=[12, 20])
    assert [lv.order for lv in levels] == [12, 20]
    for lv in levels:
        assert np.all(lv.poles_rad_s.real < 0) and np.all(lv.poles_rad_s.imag > 0)
        assert np.all((lv.freq_hz >= 50) & (lv.freq_hz <= 300)) and np.all(np.diff(lv.freq_hz) >= 0)
    for f0 in STRUCTURE.freqs_hz[2:5]:
        assert np.min(np.abs(levels[-1].freq_hz / f0 - 1)) < 1e-4


@pytest.mark.parametrize("call,source", [
    (lambda h: lscf(FREQ_HZ, h[:-1], max_order=20), "frf"),
    (lambda h: lscf(FREQ_HZ, h[..., None, None], max_order=20), "frf"),
    (lambda h: lscf(FREQ_HZ[::-1], h, max_order=20), "freq_hz"),
    (lambda h: lscf(FREQ_HZ, h, max_order=1), "max_order"),
    (lambda h: lscf(FREQ_HZ, h, max_order=20, orders=[30]), "orders"),
    (lambda h: lscf(FREQ_HZ, h, max_order=20, fmin_hz=600, fmax_hz=700), "fmin_hz"),
    (lambda h: lscf(FREQ_HZ, h, max_order=20, fmin_hz=300, fmax_hz=200), "fmin_hz"),
    (lambda h: lsfd(FREQ_HZ, h, _true_poles(), frf_kind="inertance"), "frf_kind"),
    (lambda h: lsfd(FREQ_HZ, h, _true_poles().conj(), frf_kind="accelerance"), "poles_rad_s"),
    (lambda h: lsfd(FREQ_HZ, h, _true_poles(), frf_kind="accelerance", fmin_hz=100, fmax_hz=101), "fmin_hz"),
    (lambda h: fit_modes(FREQ_HZ, h, frf_kind="accelerance", fmin_hz=5, fmax_hz=480, output_names=["a"]),
     "output_names"),
    (lambda h: fit_modes(FREQ_HZ, h, frf_kind="accelerance", fmin_hz=5, fmax_hz=480, max_order=4), "max_order"),
    (lambda h: lscf(FREQ_HZ, h, max_order=20, fmin_hz=100, fmax_hz=102), "max_order"),
    (lambda h: select_poles(stabilisation(lscf(FREQ_HZ, h, max_order=4)), min_stable=0), "min_stable"),
    (lambda h: stabilisation([]), "poles_by_order"),
])
def test_bad_input_names_the_argument(call, source):
    h = _frfs("accelerance", noise=0.0)[:, :2, 0]
    with pytest.raises(InputError) as err:
        call(h)
    assert source in err.value.source


def test_nan_frf_is_rejected():
    h = _frfs("accelerance", noise=0.0)[:, :, 0]
    h[10, 1] = np.nan
    with pytest.raises(InputError, match="frf"):
        lsfd(FREQ_HZ, h, _true_poles(), frf_kind="accelerance")
    assert isinstance(lsfd(FREQ_HZ, h[:, 0], _true_poles(), frf_kind="accelerance"), LSFDResult)
