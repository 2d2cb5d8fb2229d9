"""Shared fixtures."""

from __future__ import annotations

import pytest

from tests.factories import make_pair


@pytest.fixture
def small_pair():
    return make_pair()
