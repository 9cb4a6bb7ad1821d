"""Fixtures of the viz tests: the hand-built records of the data tests."""

import pytest

from tests.unit.data.conftest import build_record


@pytest.fixture
def make_record():
    return build_record
