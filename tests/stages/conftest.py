import pytest

from vprbench.datasets import load_dataset


@pytest.fixture(scope="session")
def stage_cache(tmp_path_factory):
    """One cache for the stage tests: hog's Corridor stores are described once."""
    return tmp_path_factory.mktemp("stage-cache")


@pytest.fixture(scope="session")
def corridor(shared_data, stage_cache):
    return load_dataset("corridor", shared_data, cache_dir=stage_cache)
