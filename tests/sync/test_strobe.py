"""Frame times from the simulated camera's exposure strobe, sampled as the DAQ samples it."""
from __future__ import annotations

import numpy as np
import pytest

from odsplat.hil_sim.camera import SimCamera, SimCameraConfig
from odsplat.hil_sim.render import PinholeCamera
from odsplat.spine.errors import InputError
from odsplat.sync.strobe import fit_strobe, strobe_edges

FS = 25_600.0
FPS = 2000.0


def _camera(scene, rng, **kw) -> SimCamera:
    pin = PinholeCamera.look_at((1.5, 0.0, 1.0), (0.2, 0.0, 0.3), fov_deg=50.0, width_px=64, height_px=48)
    return SimCamera(scene, pin, lambda t: np.zeros((6, np.size(t))), SimCameraConfig(fps=FPS),
                     clock_offset_s=rng.uniform(0, 1 / FPS), clock_drift_ppm=rng.uniform(-100, 100), **kw)


def _daq_trigger_s(t_s: float) -> float:
    return float(np.ceil(t_s * FS) / FS)  # the DAQ trigger: the first sample at or after the crossing


def test_strobe_gives_frame_times_to_a_hundredth_of_a_frame(scene):
    rng = np.random.default_rng(7)
    errors = []
    for _ in range(12):
        cam = _camera(scene, rng, drop_counters=(3, 4))  # dropped frames still strobe
        cam.arm(n_frames=60, pretrigger=10, trigger="external", at_s=0.01)
        rec = cam.trigger_at(0.05 + rng.uniform(0, 1e-3))
        volts = cam.ttl(np.arange(int(0.2 * FS)) / FS)
        st = fit_strobe(volts, FS, 0.0, rec.counters, nominal_fps=FPS,
                        trigger_time_s=_daq_trigger_s(rec.trigger_time_s))
        assert st.anchor == "end" and "anchor_mismatch" not in st.flags
        errors.append((st.frame0_start_s - rec.trigger_frame_time_s) * FPS)
        assert st.exposure_s == pytest.approx(cam.config.exposure, abs=0.002 / FPS)
        true_ppm = (1 / (1 + 1e-6 * cam.clock_drift_ppm) - 1) * 1e6
        measured_ppm = (1 / (st.period_s * FPS) - 1) * 1e6
        assert measured_ppm == pytest.approx(true_ppm, abs=400)  # 90 pulses: a rate to a few hundred ppm
        assert st.residual_frames < 0.03  # each edge within its sample: 0.29 sample rms / 12.8 samples per frame
        np.testing.assert_allclose(st.start_s(rec.counters), rec.exposure_start_s, atol=0.01 / FPS)
    assert float(np.sqrt(np.mean(np.square(errors)))) < 0.005


def test_trigger_anchor_when_the_record_ends_before_the_camera(scene):
    rng = np.random.default_rng(3)
    cam = _camera(scene, rng)
    cam.arm(n_frames=400, pretrigger=10, trigger="external", at_s=0.01)
    rec = cam.trigger_at(0.05)
    volts = cam.ttl(np.arange(int(0.1 * FS)) / FS)  # the DAQ stops while the camera still records
    st = fit_strobe(volts, FS, 0.0, rec.counters, nominal_fps=FPS, trigger_time_s=_daq_trigger_s(rec.trigger_time_s))
    assert st.anchor == "trigger"
    assert st.frame0_start_s == pytest.approx(rec.trigger_frame_time_s, abs=0.01 / FPS)
    with pytest.raises(InputError, match="cannot tell which strobe pulse"):
        fit_strobe(volts, FS, 0.0, rec.counters, nominal_fps=FPS, trigger_time_s=None)


def test_strobe_errors_name_the_channel():
    with pytest.raises(InputError, match="cam_ttl: the exposure strobe shows 0 rising edges"):
        fit_strobe(np.zeros(1000), FS, 0.0, [0, 1], nominal_fps=FPS, trigger_time_s=0.01, source="cam_ttl")
    square = (np.arange(5000) % 13 < 6).astype(float) * 5  # a strobe at 1969 fps
    with pytest.raises(InputError, match="does not match the camera's 1000 fps"):
        fit_strobe(square, FS, 0.0, [0, 1], nominal_fps=1000.0, trigger_time_s=0.01, source="cam_ttl")
    rise, fall = strobe_edges(np.array([0, 0, 5, 5, np.nan, 0, 5, 0.0]))
    np.testing.assert_allclose(rise, [1.5, 5.5])
    np.testing.assert_allclose(fall, [6.5])  # the fall into the lost sample is not trusted
