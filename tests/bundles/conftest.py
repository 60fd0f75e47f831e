"""Real runs on the real Corridor (hog, two rows) in a results store."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from vprbench.evaluation import evaluate, read_results, save_result
from vprbench.spec import RunSettings, resolve_spec


@pytest.fixture(scope="session")
def corridor_store(shared_data, tmp_path_factory) -> Path:
    """A cache whose results store holds two real hog runs on Corridor (two rows: default and resized)."""
    cache = tmp_path_factory.mktemp("contributor-store")
    settings = RunSettings(cache_dir=cache, data_dir=shared_data, workers=0)
    for options in ({}, {"resize": [96, 128]}):
        spec = resolve_spec("hog", "corridor", options=options, data_dir=shared_data, cache_dir=cache)
        save_result(evaluate(spec, settings), cache)
    return cache


@pytest.fixture
def store(corridor_store, tmp_path) -> Path:
    """A private copy of the store (a test may change it)."""
    copy = tmp_path / "store"
    shutil.copytree(corridor_store / "results", copy / "results")
    return copy


@pytest.fixture
def records(store):
    return read_results(store)
