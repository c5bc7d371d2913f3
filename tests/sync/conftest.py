"""Fixtures for the sync tests: the rig scene, and one small capture recorded on the simulated rig."""
from __future__ import annotations

import pytest

from odsplat.hil_sim.bench import SimBenchSettings, simulate_capture
from odsplat.hil_sim.camera import SimCameraConfig
from odsplat.hil_sim.scene import build_scene
from odsplat.store import Capture

FPS = 2000.0
TRIGGER_DELAY_S = 0.5 / FPS  # the simulated camera latches the trigger half a frame late, give or take
TRIGGER_JITTER_S = 0.2 / FPS


@pytest.fixture(scope="session")
def scene():
    return build_scene()


@pytest.fixture(scope="session")
def sim_capture(tmp_path_factory) -> Capture:
    """Four views on the simulated rig, each at its own random frame phase, with a trigger that lags and
    jitters, hits that vary by 30 % in force; the second take a double hit, the fourth drops two frames
    (both redone). Six takes, about 15 s."""
    out = tmp_path_factory.mktemp("sync") / "cap"
    camera = SimCameraConfig(fps=FPS, trigger_delay_s=TRIGGER_DELAY_S, trigger_jitter_s=TRIGGER_JITTER_S)
    report = simulate_capture(out, n_views=4, n_frames=60, pretrigger_frames=10, record_s=0.2,
                              settings=SimBenchSettings(camera=camera, force_scatter=0.3, seed=3),
                              faults={1: "double_hit", 3: "dropped_frames"})
    assert report.complete
    return Capture.open(out)
