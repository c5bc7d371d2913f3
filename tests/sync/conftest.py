"""Fixtures for the sync tests: the rig scene (the simulated capture is in tests/conftest.py)."""
from __future__ import annotations

import pytest

from odsplat.hil_sim.scene import build_scene

from ..conftest import FPS, TRIGGER_DELAY_S, TRIGGER_JITTER_S  # noqa: F401  (the tests import them from here)


@pytest.fixture(scope="session")
def scene():
    return build_scene()
