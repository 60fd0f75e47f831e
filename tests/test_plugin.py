"""A separately installed package adds a method through the entry point, and it is evaluated."""
import json
import os
import subprocess
import sys


def vprbench_cli(args, site, cache):
    # the tree under test stays importable (a PYTHONPATH already set), the plugin's folder first
    path = os.pathsep.join(filter(None, [str(site), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path, "VPRBENCH_CACHE": str(cache)}
    return subprocess.run([sys.executable, "-m", "vprbench.cli.main", *args], env=env, capture_output=True, text=True)


def test_plugin_is_listed_and_evaluated(example_plugin_site, shared_data, tmp_path):
    listed = vprbench_cli(["methods", "list", "--json"], example_plugin_site, tmp_path)
    entry = {m["name"]: m for m in json.loads(listed.stdout)}["thumbnail"]
    assert entry["source"] == "vprbench_example_plugin"

    run = vprbench_cli(["evaluate", "--method", "thumbnail", "--dataset", "corridor", "--data-dir", str(shared_data),
                        "--json"], example_plugin_site, tmp_path)
    assert run.returncode == 0, run.stderr
    record = json.loads(run.stdout)
    assert record["method"] == "thumbnail" and record["descriptor_dim"] == 256
    assert record["counts"]["queries"] == 111 and 0 <= record["recall"]["1"] <= 100
    assert record["provenance"]["weights"] == {"source": "none"}  # declared, as the guide shows
    assert record["origins"]["method"] == {"name": "thumbnail", "module": "vprbench_example_plugin",
                                           "distribution": "vprbench-example-plugin", "version": "0.1.0"}

    board = vprbench_cli(["leaderboard", "--format", "csv"], example_plugin_site, tmp_path)
    assert board.returncode == 0 and "thumbnail" in board.stdout
    assert "undeclared" not in board.stdout and "†" not in board.stdout, board.stdout


def test_plugin_absent_without_the_package(tmp_path):
    listed = vprbench_cli(["methods", "list", "--json"], tmp_path / "empty", tmp_path)
    assert "thumbnail" not in {m["name"] for m in json.loads(listed.stdout)}


def test_the_example_plugin_refuses_a_bad_option_in_one_line(example_plugin_site, shared_data, tmp_path):
    """The guide says a plugin raises VPRBenchError for a user error; its own example did not (a traceback)."""
    run = vprbench_cli(["evaluate", "--method", "thumbnail", "--dataset", "corridor", "--data-dir", str(shared_data),
                        "-o", "size=abc"], example_plugin_site, tmp_path)
    assert run.returncode == 1 and run.stderr.strip().splitlines() == [
        "error: thumbnail: option size takes a whole number >= 1; got 'abc'."]
