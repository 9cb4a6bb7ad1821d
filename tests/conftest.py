"""Shared pytest setup: the repo root is importable even before `pip install -e .`."""

import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# Ray must never phone home or ask for a token in tests (docs/ecosystem.md#ray).
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("RAY_AUTH_MODE", "disabled")


import pytest  # noqa: E402 - after the path setup above


@pytest.fixture
def one_torch_thread():
    """Run the test on one torch thread (restored after): small tensors run fastest on one thread, and
    a shared 2-core machine thrashes with more. Directories and modules of small-tensor tests use it
    through an autouse fixture of their own."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(autouse=True)
def _torch_threads_restored():
    """Whatever a test sets torch's thread count to (`n3dmap train` in-process gives itself every usable
    CPU) is undone after it: the suite runs two pytest processes on one thread each (scripts/test.sh), and a
    test left on two threads would make every later test in its process contend with the other process."""
    import torch

    before = torch.get_num_threads()
    yield
    if torch.get_num_threads() != before:
        torch.set_num_threads(before)
