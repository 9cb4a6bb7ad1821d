"""Small tensors run fastest on one thread; a shared 2-core machine thrashes with more."""

import pytest


@pytest.fixture(autouse=True)
def _one_torch_thread(one_torch_thread):
    """Every test here runs on one torch thread (tests/conftest.py)."""
