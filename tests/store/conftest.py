"""The store tests' methods (store_helpers.py), registered once per session."""
from __future__ import annotations

import pytest

import store_helpers


@pytest.fixture(autouse=True, scope="session")
def _test_methods():
    store_helpers.register_all()
