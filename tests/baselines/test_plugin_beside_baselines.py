"""docs/add-your-method.md end to end: the example plugin, installed as a separate package,
is listed, describes images, and lands on the leaderboard next to a baseline."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from vprbench.evaluation import read_results
from vprbench.leaderboard import leaderboard

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "add-your-method.md"
EXAMPLE = ROOT / "docs" / "examples" / "vprbench-example-plugin"


def test_doc_shows_the_example_files_verbatim():
    blocks = re.findall(r"```(?:toml|python)\n(.*?)```", DOC.read_text(), flags=re.S)
    assert (EXAMPLE / "pyproject.toml").read_text() in blocks
    assert (EXAMPLE / "vprbench_example_plugin" / "__init__.py").read_text() in blocks


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory):
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(EXAMPLE)], check=True)
    return target


def cli(args, site, cache):
    env = {**os.environ, "PYTHONPATH": str(site), "VPRBENCH_CACHE": str(cache)}
    run = subprocess.run([sys.executable, "-m", "vprbench.cli.main", *args], env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    return run.stdout


def test_plugin_listed_beside_baselines_and_describes(plugin_site, tmp_path, shared_data):
    listed = {m["name"]: m for m in json.loads(cli(["methods", "list", "--json"], plugin_site, tmp_path))}
    assert listed["thumbnail"]["source"] == "vprbench_example_plugin"
    assert listed["cosplace"]["source"] == "vprbench_baselines"
    assert listed["cosplace"]["defaults"] == {"backbone": "ResNet101", "dim": 2048}

    images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:3]
    if len(images) < 3:
        pytest.skip("corridor query images are absent")
    out = tmp_path / "d.npy"
    cli(["describe", "--method", "thumbnail", *map(str, images), "--out", str(out)], plugin_site, tmp_path)
    descriptors = np.load(out)
    assert descriptors.shape == (3, 256)
    np.testing.assert_allclose(np.linalg.norm(descriptors, axis=1), 1.0, atol=1e-5)


def test_plugin_and_baseline_share_the_leaderboard(plugin_site, tmp_path, shared_data, official_checkpoint):
    if not (shared_data / "corridor").is_dir():
        pytest.skip("corridor dataset is absent")
    state = official_checkpoint("cosplace", "ResNet18_512")
    state["aggregation.3.weight"] = state["aggregation.3.weight"][:32]
    state["aggregation.3.bias"] = state["aggregation.3.bias"][:32]
    weights = tmp_path / "ResNet18_32_cosplace.pth"
    torch.save(state, weights)
    common = ["--dataset", "corridor", "--data-dir", str(shared_data), "--json"]
    plugin = json.loads(cli(["evaluate", "--method", "thumbnail", *common], plugin_site, tmp_path))
    baseline = json.loads(cli(["evaluate", "--method", "cosplace", "--backbone", "ResNet18", "-o", "dim=32",
                               "--weights", str(weights), "--resize", "32", "32", *common], plugin_site, tmp_path))
    assert baseline["descriptor_dim"] == 32 and plugin["descriptor_dim"] == 256
    fingerprint = baseline["method_fingerprint"]
    assert fingerprint["backbone"] == "ResNet18" and fingerprint["preprocess"]["resize"] == [32, 32]
    assert len(fingerprint["weights_sha256"]) == 64
    assert baseline["counts"]["queries"] == 111 and 0 <= baseline["recall"]["1"] <= 100

    # the table 'vprbench leaderboard' prints, read from the same results store
    board = leaderboard(read_results(tmp_path))
    assert {"thumbnail", "cosplace"} <= set(board.index)
    assert board.loc["cosplace", "corridor"] == f"{baseline['recall']['1']:.1f} / {baseline['recall']['5']:.1f}"
    assert board.loc["thumbnail", "corridor"] == f"{plugin['recall']['1']:.1f} / {plugin['recall']['5']:.1f}"
