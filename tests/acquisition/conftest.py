"""Fixtures shared by the acquisition tests."""
from __future__ import annotations

import pytest

from odsplat.hil_sim.scene import build_scene


@pytest.fixture(scope="session")
def scene():
    """The default rig scene, built once: tests only read it."""
    return build_scene()
