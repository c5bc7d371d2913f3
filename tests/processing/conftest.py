"""Fixtures for the processing tests."""
from __future__ import annotations

import pytest
import torch

from .motion import texture


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Small tensors gain nothing from threads, and two threads on two shared cores run 5-10x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tex() -> torch.Tensor:
    return texture()
