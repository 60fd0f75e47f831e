import os
from pathlib import Path

import pytest

#: real public data shared beside the repo (../shared/data, or $VPRBENCH_SHARED_DATA); never copied into it
SHARED_DATA = Path(os.environ.get("VPRBENCH_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it sits beside the repo as ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def example_plugin_site(tmp_path_factory) -> Path:
    """docs/examples/vprbench-example-plugin installed, as a separate package, into its own folder."""
    import subprocess
    import sys

    example = Path(__file__).resolve().parents[1] / "docs" / "examples" / "vprbench-example-plugin"
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(example)], check=True)
    return target


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path, monkeypatch):
    """Every test writes stores, vocabularies and results under its own temporary folder."""
    monkeypatch.setenv("VPRBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("VPRBENCH_DATA", raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch-home"))


def pytest_collection_modifyitems(config, items):
    """Benchmarks (tests/benchmarks) run only when asked: pytest tests/benchmarks --benchmark-enable."""
    if config.getoption("benchmark_enable", False):
        return
    skip = pytest.mark.skip(reason="benchmark: run with --benchmark-enable")
    for item in items:
        if "benchmarks" in item.path.parts:
            item.add_marker(skip)
