"""A stage from a separate package, found through the `vprbench.stages` entry point: nothing is
installed, the package and its distribution metadata are put on the path as pip would leave them."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "vprbench-example-stage"


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The example package beside its .dist-info (METADATA + entry_points.txt from its pyproject)."""
    import tomllib

    project = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())["project"]
    site = tmp_path_factory.mktemp("site")
    shutil.copytree(EXAMPLE / "vprbench_example_stage", site / "vprbench_example_stage")
    info = site / f"vprbench_example_stage-{project['version']}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {project['name']}\nVersion: {project['version']}\n")
    points = project["entry-points"]["vprbench.stages"]
    (info / "entry_points.txt").write_text("[vprbench.stages]\n" + "".join(f"{k} = {v}\n" for k, v in points.items()))
    return site


def cli(args, site, cache):
    env = {**os.environ, "PYTHONPATH": str(site), "VPRBENCH_CACHE": str(cache)}
    return subprocess.run([sys.executable, "-m", "vprbench.cli.main", *map(str, args)], env=env, capture_output=True,
                          text=True)


def test_a_third_party_stage_is_listed_and_run(site, shared_data, stage_cache):
    listed = {s["name"]: s for s in json.loads(cli(["stages", "list", "--json"], site, stage_cache).stdout)}
    assert listed["consensus"]["source"] == "vprbench_example_stage"
    assert listed["consensus"]["options"] == {"k": 100, "n": 3, "weight": 1.0}
    run = cli(["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data, "--k", "1", "5",
               "--rerank", "consensus", "--rerank-k", "20", "--rerank-option", "n=2", "--json", "--quiet"], site, stage_cache)
    assert run.returncode == 0, run.stderr
    record = json.loads(run.stdout)
    assert record["track"] == "re-ranked" and record["stages"][0]["name"] == "consensus"
    assert record["spec"]["stages"] == [{"name": "consensus", "options": {"k": 20, "n": 2, "weight": 1.0}}]
    saved = sorted((stage_cache / "results").glob("**/*.json"))
    bad = cli(["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data,
               "--rerank", "consensus", "--rerank-option", "weight=heavy"], site, stage_cache)
    assert bad.returncode == 1 and bad.stderr.strip().splitlines() == [
        "error: Stage 'consensus' option weight: Input should be a valid number, unable to parse string as a number "
        "(got 'heavy')."]
    assert sorted((stage_cache / "results").glob("**/*.json")) == saved  # nothing written as a result


def test_without_the_package_the_stage_is_unknown(tmp_path, shared_data):
    run = cli(["evaluate", "--method", "hog", "--dataset", "corridor", "--data-dir", shared_data, "--rerank",
               "consensus"], tmp_path / "empty", tmp_path)
    assert run.returncode == 1 and "Unknown stage 'consensus'" in run.stderr


def test_a_stage_fingerprint_is_plain_data():
    import numpy as np

    from vprbench.errors import VPRBenchError
    from vprbench.stages.run import stage_fingerprint

    stage = type("S", (), {"name": "mine", "fingerprint": lambda self: {"table": np.zeros(2000)}})()
    # before: kept as the array's text, '[0. 0. 0. ... 0. 0. 0.]' whatever the array
    with pytest.raises(VPRBenchError, match=r"Stage 'mine': fingerprint\(\) holds a ndarray at table, which is "):
        stage_fingerprint(stage)
    stage.fingerprint = lambda: {"k": np.int64(4), "w": Path("a.pt")}
    assert stage_fingerprint(stage) == {"k": 4, "w": "a.pt"}
