"""A release download whose sha256 is not the one the manifest pins is refused in one line giving both
(it said "Offline?" and cut the sha256 short), nothing is kept, and the next good download runs."""
from __future__ import annotations

import hashlib

import torch

from vprbench.evaluation import read_results
from vprbench.features.backbones import create_model
from vprbench.features.catalogue import backbones
from vprbench.weights import weights_folder

from release_formats import official_state_dict
from test_bad_input_audit import assert_refused, tiny


def test_a_download_of_other_bytes_than_the_pinned_sha256_names_both(cli, shared_data, tmp_path, monkeypatch):
    spec = tiny("dinov2_vits14", monkeypatch)
    release = tmp_path / "release" / "dinov2_tiny_pretrain.pth"
    release.parent.mkdir()
    torch.save(official_state_dict(create_model(spec), spec), release)
    digest = hashlib.sha256(release.read_bytes()).hexdigest()
    # a file:// URL: torch's downloader reads it as it reads https, with no network
    pinned = spec.model_copy(update={"url": release.as_uri(), "sha256": "AB" * 32})
    monkeypatch.setitem(backbones(), spec.name, pinned)
    code, _, err = cli(
        "evaluate", "--method", "anyloc", "--backbone", spec.name, "--layer", "1", "--aggregation", "gem",
        "--dataset", "corridor", "--data-dir", shared_data, "--quiet")
    assert_refused(code, err, f"the download of dinov2_tiny_pretrain.pth from {release.as_uri()} has sha256 {digest}",
                   f"not the published {'ab' * 32}", "was not kept", "pass it with --weights PATH")
    assert "Offline" not in err
    assert not [p for p in weights_folder().glob("*") if not p.name.endswith(".lock")], "a mismatching file was kept"
    monkeypatch.setitem(backbones(), spec.name, pinned.model_copy(update={"sha256": digest}))
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", spec.name, "--layer", "1", "--aggregation",
                       "gem", "--dataset", "corridor", "--data-dir", shared_data, "--quiet")
    assert code == 0, err
    [record] = read_results()
    assert record["provenance"]["weights"] == {"source": "official", "url": release.as_uri(), "sha256": digest,
                                               "recognised_by": "sha256"}
