import pytest


def pytest_collection_modifyitems(config, items):
    """Benchmarks are slow on purpose: run them only with --benchmark-enable."""
    if config.getoption("benchmark_enable", False):
        return
    skip = pytest.mark.skip(reason="benchmark: run with --benchmark-enable")
    for item in items:
        if "benchmarks" in item.nodeid:
            item.add_marker(skip)
