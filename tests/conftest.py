import os

# xdist runs one worker per core, each with OpenMP threads of its own (torch, faiss): an idle thread sleeps
# instead of spinning on a core another worker needs (on 2 cores, spinning made faiss's training 2 to 4 x
# slower). Set before any OpenMP library loads; the thread counts, and so the results, are unchanged.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pathlib import Path
from types import SimpleNamespace

import pytest

import pitts30k_tree as pitts30k_tree_module  # tests/ is on sys.path (pytest's rootdir conftest)
import utm_trees

#: real public data shared beside the repo (../shared/data, or $VPRBENCH_SHARED_DATA); never copied into it
SHARED_DATA = Path(os.environ.get("VPRBENCH_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


#: set by .ci/run: the real data must be there, and every real-data test that skips is named
IN_CI = os.environ.get("VPRBENCH_CI") == "1"


def pytest_sessionstart(session):
    if IN_CI and not SHARED_DATA.is_dir():
        raise pytest.UsageError(
            f"CI needs the real data folder {SHARED_DATA} (../shared/data beside the repo, or $VPRBENCH_SHARED_DATA): "
            "without it the real-data tests would be skipped and the run would prove nothing. Put the data there.")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it sits beside the repo as ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def shared_reference(shared_data) -> Path:
    """The AnyLoc paper's facts and tables as data (../shared/reference, beside the real data)."""
    folder = shared_data.parent / "reference"
    if not (folder / "anyloc-paper-results.csv").is_file():
        pytest.skip(f"reference folder {folder} is absent (it sits beside the repo as ../shared/reference)")
    return folder


def pytest_terminal_summary(terminalreporter):
    """In CI, a real-data test that skipped (for any reason: no browser, no mount permission...) is named."""
    if not IN_CI:
        return
    skipped = [r for r in terminalreporter.stats.get("skipped", []) if "shared_data" in getattr(r, "fixturenames", ())]
    if skipped:
        terminalreporter.section("real-data tests that skipped")
        for report in skipped:
            reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
            terminalreporter.write_line(f"{report.nodeid}: {reason}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    outcome.get_result().fixturenames = tuple(item.fixturenames)  # for the summary above


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
    """Every test writes stores, vocabularies and results under its own temporary folder, which is
    both the command line's default ($VPRBENCH_CACHE) and the library's (the user cache, under
    $XDG_CACHE_HOME)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user-cache"))
    monkeypatch.setenv("VPRBENCH_CACHE", str(tmp_path / "user-cache" / "vprbench"))
    monkeypatch.delenv("VPRBENCH_DATA", raising=False)


def pytest_collection_modifyitems(config, items):
    """Benchmarks (tests/benchmarks) run only when asked: pytest tests/benchmarks --benchmark-enable."""
    if config.getoption("benchmark_enable", False):
        return
    skip = pytest.mark.skip(reason="benchmark: run with --benchmark-enable")
    for item in items:
        if "benchmarks" in item.path.parts:
            item.add_marker(skip)


# ---------------------------------------------------------------- a full-size Pitts-30k test tree
@pytest.fixture(scope="session")
def pitts30k_tree(tmp_path_factory, shared_data) -> SimpleNamespace:
    """The 10,000 database and 6,816 query images of Pitts-30k test (tests/pitts30k_tree.py)."""
    return pitts30k_tree_module.build(shared_data, tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="session")
def pitts30k_places(pitts30k_tree) -> dict:
    return pitts30k_tree_module.oracle_places(pitts30k_tree)


# ------------------------------------- full-size trees of the largest utm-names datasets
@pytest.fixture(scope="session")
def pitts250k_tree(tmp_path_factory, shared_data) -> SimpleNamespace:
    """83,952 database and 8,280 query images at synthetic positions (tests/utm_trees.py)."""
    return utm_trees.build_pitts250k(shared_data, tmp_path_factory.mktemp("data"))


@pytest.fixture(scope="session")
def tokyo247_tree(tmp_path_factory, shared_data) -> SimpleNamespace:
    """75,984 database and 315 query images at Tokyo 24/7's real positions (tests/utm_trees.py)."""
    return utm_trees.build_tokyo247(shared_data, tmp_path_factory.mktemp("data"))


@pytest.fixture
def cli(capsys):
    """cli(*args) -> (exit code, stdout, stderr) of the vprbench command, in process."""
    from vprbench.cli.main import main

    def run(*args) -> tuple[int, str, str]:
        try:
            code = main([str(a) for a in args])
        except SystemExit as usage_error:  # argparse's: exit code 2
            code = usage_error.code
        out, err = capsys.readouterr()
        return code, out, err

    return run


# ---------------------------------------------------------------- the method and stage registries, the test's own
class ScratchRegistry:
    """A registry (vprbench.registration.Registry) whose state is one test's; `module` is the module it is in."""

    def __init__(self, module, registry, monkeypatch):
        self.module, self.registry, self._monkeypatch = module, registry, monkeypatch

    def fresh(self, *plugins) -> None:
        """The registry as a new process finds it, with `plugins` (entry points: .name, .value, .load()) the only
        ones installed: nothing registered yet; its first use registers the core's entries, then runs `plugins`."""
        for name, value in (("entries", {}), ("loaded", False), ("failures", []), ("installed", lambda: list(plugins))):
            self._monkeypatch.setattr(self.registry, name, value)


def _scratch(module, registry, monkeypatch) -> ScratchRegistry:
    registry.load()  # loaded first, whichever test is a process's first to use it: the state put back after each test
    for name, copied in (("entries", dict), ("loaded", bool), ("failures", list)):
        monkeypatch.setattr(registry, name, copied(getattr(registry, name)))
    return ScratchRegistry(module, registry, monkeypatch)


@pytest.fixture
def scratch_methods(monkeypatch) -> ScratchRegistry:
    """The method registry as this test's own copy, which it may register into: the core's and the installed
    plugins' methods (loaded first; the plugins that failed to load still named); what the test registers or
    changes is gone after it. `scratch_methods.fresh(*plugins)` makes it the registry of a new process instead."""
    from vprbench.methods import registry

    return _scratch(registry, registry.METHODS, monkeypatch)


@pytest.fixture
def scratch_stages(monkeypatch) -> ScratchRegistry:
    """The stage registry as this test's own copy, as `scratch_methods` makes the method registry's."""
    from vprbench.stages import registry

    return _scratch(registry, registry.STAGES, monkeypatch)
