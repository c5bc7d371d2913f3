"""Output-only modal analysis (odsplat.analysis.oma.identify) against the truth and against pyOMA2.

Cases: (a) `ambient`, a 3-mode system (31, 77, 140 Hz; 1, 1.5, 2 % damping; 12 channels at 500 Hz) driven by white
noise for 120 s, simulated exactly (each mode's zero-order-hold discretisation), plus white measurement noise of
3.5-7 % of the response's RMS; (b) `decay`, the same system's free decay over 3 s with 1-2 % noise; (c) `ladisk`,
the LADISK beam's video displacements (15 points, image axis 0, 15 000 fps, 0.25 s), against its accelerometer's
modes (695.8, 1898.0, 2777.6 Hz), when ../shared/data (or ODSPLAT_SHARED_DATA, or --shared-data) holds it.

Figures per case: ours (automatic selection): frequencies, dampings, their largest relative errors against the
reference, the MAC of the shapes against the truth (synthetic cases) and the wall time. pyOMA2 (when installed):
its SSI-cov with the same block rows and largest order, its modes taken at order 30 nearest the reference
frequencies (its `mpe`, which needs them: it has no automatic selection without its clustering), and its FDD peak
picking at the same frequencies; wall time of its run and mpe, and ours over theirs (`time_ratio`, below 1: ours is
faster). Baseline in every case: the FDD peak nearest each reference (ours, `FDDResult.peaks_hz`).

Prints one JSON line on stdout; progress goes to stderr. About 12 s on 2 busy cores (pyOMA2's SSI on the 120 s
ambient case takes most).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
from scipy.signal import cont2discrete, lfilter

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from odsplat.analysis.correlation import mac  # noqa: E402
from odsplat.analysis.oma import identify  # noqa: E402
from odsplat.spine.shared_data import shared_data_dir  # noqa: E402

log = logging.getLogger("bench.oma")

FS_HZ = 500.0
FREQ_HZ = np.array([31.0, 77.0, 140.0])
DAMPING = np.array([0.01, 0.015, 0.02])
N_CH = 12
LADISK_HZ = [695.8, 1898.0, 2777.6]          # the accelerometer's (../shared/data/README.md, tests/analysis)
LADISK_DAMPING = [0.0047, 0.0031, 0.0024]
PYOMA2_ORDER = 30


def true_shapes() -> np.ndarray:
    pos = (np.arange(N_CH) + 0.5) / N_CH
    return np.stack([np.sin((r + 1) * np.pi * pos) for r in range(3)])


def modal_response(forces: np.ndarray) -> np.ndarray:
    """Displacements (T, N_CH) under modal forces (T, 3) held over each sample (exact for that input)."""
    q = np.empty_like(forces)
    for r, (f, z) in enumerate(zip(FREQ_HZ, DAMPING)):
        w = 2 * np.pi * f
        b, a, _ = cont2discrete(([1.0], [1.0, 2 * z * w, w * w]), 1 / FS_HZ, method="zoh")
        q[:, r] = lfilter(np.ravel(b), a, forces[:, r])
    return q @ true_shapes()


def synthetic(kind: str, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    if kind == "ambient":
        y = modal_response(rng.standard_normal((int(120 * FS_HZ), 3)) * np.sqrt(DAMPING * (FREQ_HZ / 31.0) ** 3))
        sigma = 0.035 * y.std() * np.linspace(1.0, 2.0, N_CH)
    else:
        impulse = np.zeros((int(3 * FS_HZ), 3))
        impulse[0] = FREQ_HZ
        y = modal_response(impulse)
        sigma = 0.01 * np.abs(y).max() * np.linspace(1.0, 2.0, N_CH)
    return y + sigma * rng.standard_normal(y.shape)


def _errors(freq, damping, ref_freq, ref_damping) -> dict:
    """Each reference's nearest found mode: the largest relative errors, and the references with none within 1 %."""
    freq, damping = np.asarray(freq, float), np.asarray(damping, float)
    if freq.size == 0:
        return {"max_freq_err": None, "max_damping_err": None, "missed_hz": list(ref_freq)}
    near = [int(np.argmin(np.abs(freq - f))) for f in ref_freq]
    f_err = np.abs(freq[near] / np.asarray(ref_freq) - 1)
    out = {"max_freq_err": float(f_err.max()), "missed_hz": [f for f, e in zip(ref_freq, f_err) if e > 0.01]}
    if damping.size:
        out["max_damping_err"] = float(np.max(np.abs(damping[near] / np.asarray(ref_damping) - 1)))
    return out


def _pyoma2(x: np.ndarray, fs: float, ref_hz, n_lags: int, max_order: int, nperseg: int) -> dict | None:
    try:
        from pyoma2.algorithms import FDD, SSI
        from pyoma2.setup import SingleSetup
    except ImportError as exc:
        log.warning("pyOMA2 is not installed (%s): no comparison", exc)
        return None
    logging.getLogger("pyoma2").setLevel(logging.ERROR)
    t0 = time.perf_counter()
    setup = SingleSetup(x, fs=fs)
    ssi = SSI(name="SSIcov", method="cov", br=n_lags, ordmax=max_order)
    fdd = FDD(name="FDD", nxseg=nperseg, method_SD="per")
    setup.add_algorithms(ssi, fdd)
    setup.run_all()
    setup.mpe("SSIcov", sel_freq=list(ref_hz), order_in=PYOMA2_ORDER)
    setup.mpe("FDD", sel_freq=list(ref_hz), DF=2 * fs / nperseg)
    return {"freq_hz": np.asarray(ssi.result.Fn, float).tolist(), "damping": np.asarray(ssi.result.Xi).tolist(),
            "fdd_freq_hz": np.asarray(fdd.result.Fn, float).tolist(), "phi": np.asarray(ssi.result.Phi).T,
            "seconds": time.perf_counter() - t0}


def run_case(name: str, x: np.ndarray, fs: float, ref_hz, ref_damping, shapes: np.ndarray | None,
             band: dict) -> dict:
    log.info("%s: %d samples x %d channels", name, *x.shape)
    t0 = time.perf_counter()
    res = identify(x, fs, **band)
    ours_s = time.perf_counter() - t0
    peaks = res.fdd.peaks_hz(*res.band_hz)
    out = {"ours": {"freq_hz": res.freq_hz.round(3).tolist(), "damping": res.damping.round(5).tolist(),
                    "mpc": res.mpc.round(4).tolist(), "seconds": round(ours_s, 3),
                    "harmonics_hz": [round(m.freq_hz, 2) for m in res.harmonics],
                    **_errors(res.freq_hz, res.damping, ref_hz, ref_damping)},
           "fdd_peak_baseline": {"freq_hz": [float(peaks[np.argmin(np.abs(peaks - f))]) for f in ref_hz]
                                 if peaks.size else [], **_errors(peaks, [], ref_hz, ref_damping)},
           "reference_hz": list(map(float, ref_hz))}
    if shapes is not None and res.freq_hz.size:
        near = [int(np.argmin(np.abs(res.freq_hz - f))) for f in ref_hz]
        out["ours"]["mac"] = np.diag(mac(res.shapes[near], shapes)).round(5).tolist()
    theirs = _pyoma2(x, fs, ref_hz, res.n_lags, 60, res.fdd.nperseg)
    if theirs is not None:
        phi = theirs.pop("phi")
        if shapes is not None:
            theirs["mac"] = np.diag(mac(phi, shapes)).round(5).tolist()
        theirs.update(_errors(theirs["freq_hz"], theirs["damping"], ref_hz, ref_damping))
        theirs["fdd_max_freq_err"] = _errors(theirs["fdd_freq_hz"], [], ref_hz, ref_damping)["max_freq_err"]
        theirs["seconds"] = round(theirs["seconds"], 3)
        out["pyoma2"] = theirs
        out["time_ratio"] = round(ours_s / theirs["seconds"], 3)
        out["ours_vs_pyoma2_max_freq_diff"] = float(np.max(np.abs(
            np.array([res.freq_hz[np.argmin(np.abs(res.freq_hz - f))] for f in theirs["freq_hz"]])
            / np.array(theirs["freq_hz"]) - 1))) if res.freq_hz.size else None
    return out


def _shared_data(arg: str | None) -> Path:
    if arg:
        return Path(arg)
    return shared_data_dir(REPO)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1, help="the synthetic cases' random seed")
    ap.add_argument("--shared-data", help="the folder of real recordings (default ../shared/data)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(name)s: %(message)s")
    band = {"fmin_hz": 10.0, "fmax_hz": 200.0}
    figures = {"bench": "oma", "seed": args.seed, "cases": {}}
    for kind in ("ambient", "decay"):
        figures["cases"][kind] = run_case(kind, synthetic(kind, args.seed), FS_HZ, FREQ_HZ.tolist(),
                                          DAMPING.tolist(), true_shapes(), band)
    path = _shared_data(args.shared_data) / "ladisk-imaging-tutorial" / "displacements_lk.npy"
    if path.is_file():
        x = np.load(path)[:, :, 0].T
        figures["cases"]["ladisk"] = run_case("ladisk", x, 15000.0, LADISK_HZ, LADISK_DAMPING, None,
                                              {"fmin_hz": 100.0, "fmax_hz": 5000.0})
    else:
        log.warning("no LADISK data at %s: that case is skipped", path)
    print(json.dumps(figures, default=float))
    return figures


if __name__ == "__main__":
    main()
