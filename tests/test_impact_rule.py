"""One impact rule for every stage (odsplat.spine.impulse.ImpactDetector): a hammer record with a rebound of a
given size is judged alike by hit QC, sync, the FRF's hit check and split_hits, and the one constant
(REBOUND_FRACTION) or the one settings field (ImpactSettings.rebound_fraction) moves them all."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from odsplat.acquisition import QCLimits, QCSettings, run_qc
from odsplat.acquisition.daq import DAQChannel
from odsplat.acquisition.qc import check_hit, check_take
from odsplat.acquisition.trigger import TriggeredRecord
from odsplat.analysis import FRFSettings, check_frf_hit, estimate_frf, split_hits
from odsplat.spine import impulse
from odsplat.spine.impulse import REBOUND_FRACTION, ImpactSettings, fit_pulse, half_sine
from odsplat.spine.store import Capture
from odsplat.sync import SyncSettings, sync_capture

pytestmark = pytest.mark.timeout(180)
FS = 25_600.0
# A rebound of this fraction of the main peak, 3 ms after it: two well under the default threshold, two a little
# either side of it, one well over.
RATIOS = {"r03": 0.03, "under": REBOUND_FRACTION - 0.004, "over": REBOUND_FRACTION + 0.004, "r07": 0.07}
DEFAULT_DOUBLE = {"r03": False, "under": False, "over": True, "r07": True}


def _with_rebound(force: np.ndarray, fs: float, ratio: float) -> np.ndarray:
    """The force with a half sine of `ratio` times its largest sample added, two pulse lengths after its onset."""
    p = fit_pulse(force, fs)
    tau = p.duration_s * fs
    return force + half_sine(np.arange(force.size, dtype=float), p.onset_sample + 2 * tau + 0.37, ratio * force.max(),
                             tau)


# ------------------------------------------------------------------------------------- synthetic records

def _synthetic(ratio: float, seed: int) -> np.ndarray:
    """0.2 s of a 1 ms, 180 N half sine at 20 ms (and its rebound), on a 0.4 N offset with 0.1 N of noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(0.2 * FS), dtype=float)
    clean = half_sine(t, 0.02 * FS + rng.uniform(0, 1), 180.0, 1e-3 * FS)
    force = clean if ratio == 0 else _with_rebound(clean, FS, ratio)
    return force + 0.4 + 0.1 * rng.standard_normal(t.size)


def _synthetic_verdicts(forces: dict[str, np.ndarray], impacts: ImpactSettings | None) -> dict[str, dict[str, bool]]:
    """Whether each stage calls each record a double hit: QC's check_hit, the FRF's check, split_hits."""
    channels = [DAQChannel("force", 0, "force", 2.25e-3)]
    limits = QCLimits() if impacts is None else QCLimits(impacts=impacts)
    out = {}
    for name, f in forces.items():
        record = TriggeredRecord(int(0.02 * FS), 0, f.size, FS, ("force",), f[None])
        qc = check_hit(record, channels, limits=limits)
        frf = check_frf_hit(f, FS, impacts=impacts)
        seg = split_hits(f, np.zeros(f.size), FS, pretrigger_s=0.005, length_s=0.1, impacts=impacts)
        assert frf.n_impacts == len(qc.impact_times_s) == seg.n_impacts[0], name
        out[name] = {"qc": "double_hit" in qc.reasons, "frf": not frf.accepted, "split_hits": seg.n_impacts[0] > 1}
    return out


def _all(verdicts: dict[str, dict[str, bool]]) -> dict[str, bool]:
    """Each record's verdict, once every stage agrees on it (an assertion otherwise)."""
    for name, by_stage in verdicts.items():
        assert len(set(by_stage.values())) == 1, (name, by_stage)
    return {name: next(iter(v.values())) for name, v in verdicts.items()}


def test_synthetic_rebounds_are_judged_alike_by_every_stage(monkeypatch):
    forces = {name: _synthetic(r, k) for k, (name, r) in enumerate(RATIOS.items())}
    forces["clean"] = _synthetic(0.0, 9)
    assert _all(_synthetic_verdicts(forces, None)) == {**DEFAULT_DOUBLE, "clean": False}
    # The settings field moves every stage ...
    low = ImpactSettings(rebound_fraction=0.02)
    assert _all(_synthetic_verdicts(forces, low)) == {**dict.fromkeys(RATIOS, True), "clean": False}
    # ... and so does the one constant, through every default.
    monkeypatch.setattr(impulse, "REBOUND_FRACTION", 0.08)
    assert ImpactSettings().rebound_fraction == QCLimits().impacts.rebound_fraction == 0.08
    assert _all(_synthetic_verdicts(forces, None)) == dict.fromkeys([*RATIOS, "clean"], False)


def test_the_stages_default_to_the_one_constant():
    for impacts in (QCLimits().impacts, QCSettings().impacts, FRFSettings().impacts, SyncSettings().impacts):
        assert impacts.rebound_fraction == REBOUND_FRACTION
    assert SyncSettings().impacts.min_peak_n == 5.0  # sync's own floor: a peak under 5 N is noise, not a hit


# ------------------------------------------------------------------- takes recorded on the simulated rig

def _add_takes(cap: Capture, source: str, ratios: dict[str, float]) -> float:
    """Copies of take `source` with a rebound of each ratio added to its force; returns the main peak (N)."""
    with cap.open_take(source) as r:
        fs = r.sample_rate_hz
        force = r.channel("force").astype(float)
        for name, ratio in ratios.items():
            w = cap.new_take(name, view=r.view, frame_shape=r.frame_shape, dtype=r.frames.dtype, bit_depth=r.bit_depth,
                             fps=r.fps, daq_t0_s=r.daq_t0_s, channels=[r.channel_info(n) for n in r.channel_names])
            with w:
                w.append_samples({n: _with_rebound(force, fs, ratio) if n == "force" else r.channel(n)
                                  for n in r.channel_names})
                w.append_frames(r.read_frames(), r.frame_times_s, r.frame_counter)
                w.set_trigger(r.trigger)
                w.set_qc(r.qc)
                w.finalize()
    return float(force.max())


@pytest.fixture(scope="module")
def rebound_capture(sim_capture, tmp_path_factory) -> Capture:
    """The simulated rig's capture, with copies of a clean take whose force has a rebound of each size."""
    dest = tmp_path_factory.mktemp("rebounds") / "cap"
    shutil.copytree(sim_capture.root, dest, ignore=shutil.ignore_patterns("derived"))
    cap = Capture.open(dest)
    peak = _add_takes(cap, "v00_000", {**RATIOS, "clean": 0.0})
    assert 100 < peak < 400
    return Capture.open(dest)


def _take_verdicts(cap: Capture, impacts: ImpactSettings | None) -> dict[str, dict[str, bool]]:
    """Whether each stage calls each rebound take a double hit, from the take files: QC (check_take and the qc
    stage's qc.json), sync (the take excluded as a double hit), the FRF (estimate_frf over the takes' hits) and
    split_hits (over the takes' records end to end)."""
    names = [*RATIOS, "clean"]
    qc = run_qc(cap, None if impacts is None else QCSettings(impacts=impacts))
    from_file = {t.name: t for t in qc.takes}
    sync_impacts = {} if impacts is None else {"impacts": impacts}
    synced = sync_capture(cap, SyncSettings(takes="all", write_frames=False, check_with_image=False, plot=False,
                                            **sync_impacts), progress=False)
    by_name = {t.name: t for t in synced.takes}
    forces, responses, out = [], [], {}
    for name in names:
        with cap.open_take(name) as r:
            fs = r.sample_rate_hz
            hit = check_take(r, QCLimits() if impacts is None else QCLimits(impacts=impacts))
            forces.append(r.channel("force").astype(float))
            responses.append(np.stack([r.channel(n) for n in r.channels_of_kind("acceleration")]).astype(float))
        assert from_file[name].n_impacts == len(hit.impact_times_s)
        s = by_name[name]
        assert (s.hit_daq_time_s is None) == (s.error or "").startswith("force: 2 hits found"), s.error
        out[name] = {"check_take": "double_hit" in hit.reasons, "qc.json": "double_hit" in from_file[name].reasons,
                     "sync": s.hit_daq_time_s is None}
    frf = estimate_frf(np.array(forces), np.array(responses), fs,
                       FRFSettings() if impacts is None else FRFSettings(impacts=impacts))
    seg = split_hits(np.concatenate(forces), np.concatenate(responses, axis=1), fs, pretrigger_s=0.01, length_s=0.15,
                     impacts=impacts)
    assert seg.force.shape[0] == len(names)
    for k, name in enumerate(names):
        out[name] |= {"frf": not frf.hits[k].accepted, "split_hits": bool(seg.n_impacts[k] > 1)}
        assert frf.hits[k].n_impacts == seg.n_impacts[k]
    return out


def test_rig_takes_with_rebounds_are_judged_alike_by_every_stage(rebound_capture, monkeypatch):
    cap = rebound_capture
    assert _all(_take_verdicts(cap, None)) == {**DEFAULT_DOUBLE, "clean": False}
    assert _all(_take_verdicts(cap, ImpactSettings(rebound_fraction=0.02, min_peak_n=5.0))) == {
        **dict.fromkeys(RATIOS, True), "clean": False}
    monkeypatch.setattr(impulse, "REBOUND_FRACTION", 0.08)
    assert _all(_take_verdicts(cap, None)) == dict.fromkeys([*RATIOS, "clean"], False)
    # qc.json records the settings that judged the takes (written and read back through odsplat.spine.qcfile), and
    # the store selects the imported takes by the same verdicts.
    assert run_qc(cap).settings.impacts.rebound_fraction == 0.08
    assert cap.qc_verdicts()["r07"] == "accepted"
