"""Fixtures for the processing tests."""
from __future__ import annotations

import pytest
import torch

from .motion import texture


@pytest.fixture(scope="module")
def tex() -> torch.Tensor:
    return texture()
