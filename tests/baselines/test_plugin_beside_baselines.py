"""docs/add-your-method.md end to end: the example plugin, installed as a separate package,
is listed, describes images, and lands on the leaderboard next to a baseline."""
import json
import re
import sys
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np
import pytest
import torch

from vprbench.cli.main import main as vprbench_cli
from vprbench.methods import registry

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "add-your-method.md"
EXAMPLE = ROOT / "docs" / "examples" / "vprbench-example-plugin"


def test_doc_shows_the_example_files_verbatim():
    blocks = re.findall(r"```(?:toml|python)\n(.*?)```", DOC.read_text(), flags=re.S)
    assert (EXAMPLE / "pyproject.toml").read_text() in blocks
    assert (EXAMPLE / "vprbench_example_plugin" / "__init__.py").read_text() in blocks


@pytest.fixture
def with_plugin(example_plugin_site, monkeypatch, shared_data, scratch_methods):
    """The plugin's folder on the import path, as after 'pip install'; the method registry a new process's, which
    finds the entry points installed now, the plugin's among them.
    (In-process rather than a subprocess per command: each would import torch again.)"""
    if not (shared_data / "corridor").is_dir():
        pytest.skip("corridor dataset is absent")
    monkeypatch.syspath_prepend(str(example_plugin_site))
    scratch_methods.fresh(*entry_points(group=registry.ENTRY_POINT_GROUP))
    monkeypatch.setenv("VPRBENCH_DATA", str(shared_data))  # the CLI's --data-dir sets it; undone after the test
    yield
    sys.modules.pop("vprbench_example_plugin", None)


def run(capsys, *args) -> str:
    capsys.readouterr()
    code = vprbench_cli(list(args))
    out, err = capsys.readouterr()
    assert code == 0, err
    return out


def test_plugin_listed_beside_baselines_and_describes(with_plugin, capsys, tmp_path, shared_data):
    listed = {m["name"]: m for m in json.loads(run(capsys, "methods", "list", "--json"))}
    assert listed["thumbnail"]["source"] == "vprbench_example_plugin"
    assert listed["cosplace"]["source"] == "vprbench_baselines"
    assert listed["cosplace"]["defaults"] == {"backbone": "ResNet101", "dim": 2048}

    images = sorted((shared_data / "corridor" / "query").glob("*.jpg"))[:3]
    out = tmp_path / "d.npy"
    run(capsys, "describe", "--method", "thumbnail", *map(str, images), "--out", str(out))
    descriptors = np.load(out)
    assert descriptors.shape == (3, 256)
    np.testing.assert_allclose(np.linalg.norm(descriptors, axis=1), 1.0, atol=1e-5)


def test_plugin_and_baseline_share_the_leaderboard(with_plugin, capsys, tmp_path, shared_data, official_checkpoint):
    state = official_checkpoint("cosplace", "ResNet18_512")
    state["aggregation.3.weight"] = state["aggregation.3.weight"][:32]
    state["aggregation.3.bias"] = state["aggregation.3.bias"][:32]
    weights = tmp_path / "ResNet18_32_cosplace.pth"
    torch.save(state, weights)
    common = ["--dataset", "corridor", "--data-dir", str(shared_data), "--json"]
    plugin = json.loads(run(capsys, "evaluate", "--method", "thumbnail", *common))
    baseline = json.loads(run(capsys, "evaluate", "--method", "cosplace", "--backbone", "ResNet18", "-o", "dim=32",
                              "--weights", str(weights), "--resize", "32", "32", *common))
    assert baseline["descriptor_dim"] == 32 and plugin["descriptor_dim"] == 256
    fingerprint = baseline["method_fingerprint"]
    assert fingerprint["backbone"] == "ResNet18" and fingerprint["preprocess"]["resize"] == [32, 32]
    assert len(fingerprint["weights_sha256"]) == 64
    assert baseline["counts"]["queries"] == 111 and 0 <= baseline["recall"]["1"] <= 100

    rows = {line.split(" †")[0].split(",")[0]: line for line in run(capsys, "leaderboard", "--format", "csv").splitlines()[1:]}
    cosplace = "cosplace [backbone=ResNet18 dim=32 resize=32x32]"  # options on top of the preset label the row
    assert {"thumbnail", cosplace} <= set(rows)
    assert "user weights sha256:" in rows[cosplace] and " †" in rows[cosplace]  # a user's file: a marked row
    # the plugin declares provenance as the guide shows (nothing learnt): its official row, unmarked
    assert "none (nothing learnt)" in rows["thumbnail"] and "†" not in rows["thumbnail"]
    assert f"{baseline['recall']['1']:.1f} / {baseline['recall']['5']:.1f}" in rows[cosplace]
    assert f"{plugin['recall']['1']:.1f} / {plugin['recall']['5']:.1f}" in rows["thumbnail"]


def test_the_weights_snippet_builds_a_method_from_the_run_cache(tmp_path, monkeypatch):
    # section 5's factory, copied into a package of one's own: with no --weights it finds the release
    # in <cache>/torch of the run's cache_dir (put there as a download would), so it must take cache_dir
    (snippet,) = [b for b in re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S) if "load_checkpoint" in b]
    package = tmp_path / "my_package"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "network.py").write_text(
        "import torch\n\nclass MyNet(torch.nn.Module):\n"
        "    def __init__(self):\n        super().__init__()\n        self.proj = torch.nn.Linear(3, 512)\n\n"
        "    def forward(self, x):\n        return self.proj(x.mean((2, 3)))\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    try:
        from my_package.network import MyNet

        scope: dict = {}
        exec(compile(snippet, str(DOC), "exec"), scope)
        # downloaded by vprbench (a file put there by hand would be the user's), then found there offline
        monkeypatch.setattr(torch.hub, "download_url_to_file", lambda url, to, **kw: torch.save(MyNet().state_dict(), to))
        scope["my_net"](resize=(32, 32), cache_dir=tmp_path / "cache")
        monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **kw: pytest.fail("downloaded again"))
        method = scope["my_net"](resize=(32, 32), cache_dir=tmp_path / "cache")
        assert (tmp_path / "cache" / "torch" / "hub" / "checkpoints" / "my_net_512.pth").is_file()
        assert method.fingerprint()["weights_url"] == "https://example.org/my_net_512.pth"
        assert method.provenance()["weights"]["source"] == "official"
    finally:
        for name in ("my_package", "my_package.network"):
            sys.modules.pop(name, None)


def test_the_baselines_table_lists_every_released_mixvpr_dimension():
    # section "Baselines and where their weights come from": mixvpr's row names its -o dim choices
    from vprbench_baselines.mixvpr import CONFIGS

    (row,) = [line for line in DOC.read_text().splitlines() if line.startswith("| `mixvpr`")]
    assert all(str(dim) in row for dim in CONFIGS), row
