"""A file under a release's name in the cache's checkpoint folder is not the release by its name: it is
official only when vprbench recorded downloading these very bytes from the release, or its sha256 is a
published one. Otherwise it is the user's file, exactly as the same bytes given with --weights PATH
(a random ViT put there was recorded "official, recognised by download" and filled an official cell)."""
from __future__ import annotations

import hashlib

import pytest
import torch

from vprbench.evaluation import read_results
from vprbench.features.backbones import create_model
from vprbench.features.catalogue import backbones
from vprbench.weights import weights_folder

from release_formats import official_state_dict
from test_bad_input_audit import tiny


def _run(cli, shared_data, name, *more):
    return cli("evaluate", "--method", "anyloc", "--backbone", name, "--layer", "1", "--aggregation", "gem",
               "--resize", "28", "42", "--dataset", "corridor", "--data-dir", shared_data, "--quiet", *more)


def _weights(record) -> dict:
    return record["provenance"]["weights"]


def test_a_file_put_in_the_checkpoint_folder_is_the_users_until_vprbench_downloads_it(cli, shared_data, tmp_path,
                                                                                     monkeypatch):
    spec = tiny("dinov2_vits14", monkeypatch)
    release = tmp_path / "release" / spec.file_name
    release.parent.mkdir()
    torch.manual_seed(0)
    torch.save(official_state_dict(create_model(spec), spec), release)
    digest = hashlib.sha256(release.read_bytes()).hexdigest()
    # a file:// URL: torch's downloader reads it as it reads https, with no network
    monkeypatch.setitem(backbones(), spec.name, spec.model_copy(update={"url": release.as_uri(), "sha256": None}))
    placed = weights_folder() / spec.file_name
    placed.parent.mkdir(parents=True)
    placed.write_bytes(release.read_bytes())  # as the dry run's offline advice has it put there

    with pytest.warns(UserWarning, match=f"is not a file vprbench downloaded .* 'user weights sha256:{digest[:12]}'"):
        code, _, err = _run(cli, shared_data, spec.name)
    assert code == 0 and "Traceback" not in err
    code, _, err = _run(cli, shared_data, spec.name, "--weights", release)
    assert code == 0, err
    by_name, given = read_results()
    assert _weights(by_name) == _weights(given) == {"source": "user", "sha256": digest}  # same bytes, same status
    code, out, _ = cli("leaderboard", "--format", "csv")
    rows = out.strip().splitlines()[1:]
    assert code == 0 and len(rows) == 2 and all(f"† user weights sha256:{digest[:12]}" in row for row in rows), out

    placed.unlink()  # downloaded by vprbench now: the record of the download proves these bytes
    code, _, err = _run(cli, shared_data, spec.name)
    assert code == 0 and "not a file vprbench downloaded" not in err, err
    downloaded = [r for r in read_results() if _weights(r)["source"] == "official"]
    assert [_weights(r) for r in downloaded] == [{"source": "official", "url": release.as_uri(), "sha256": digest,
                                                  "recognised_by": "download"}]

    torch.manual_seed(1)  # other bytes under the downloaded name: the record is of the bytes, not the name
    torch.save(official_state_dict(create_model(spec), spec), placed)
    with pytest.warns(UserWarning, match="is not a file vprbench downloaded"):
        code, _, err = _run(cli, shared_data, spec.name)
    assert code == 0, err
    other = hashlib.sha256(placed.read_bytes()).hexdigest()
    assert {"source": "user", "sha256": other} in [_weights(r) for r in read_results()]


def test_a_file_whose_sha256_is_published_is_official_wherever_it_came_from(cli, shared_data, tmp_path, monkeypatch):
    spec = tiny("dinov2_vits14", monkeypatch)
    placed = weights_folder() / spec.file_name
    placed.parent.mkdir(parents=True)
    torch.manual_seed(0)
    torch.save(official_state_dict(create_model(spec), spec), placed)
    digest = hashlib.sha256(placed.read_bytes()).hexdigest()
    url = f"https://example.org/{spec.file_name}"
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **k: pytest.fail("downloaded"))
    monkeypatch.setitem(backbones(), spec.name, spec.model_copy(update={"url": url, "sha256": digest}))
    code, _, err = _run(cli, shared_data, spec.name)
    assert code == 0 and "not a file vprbench downloaded" not in err, err
    [record] = read_results()
    assert _weights(record) == {"source": "official", "url": url, "sha256": digest, "recognised_by": "sha256"}


def test_vocabularies_of_the_official_weights_are_not_served_to_a_file_put_in_the_cache(tmp_path, monkeypatch):
    """The key vocabularies are cached and released under (official weights: the backbone's bare name)
    follows the same proof: a file put there by hand has the key its --weights PATH would have."""
    from vprbench.methods.anyloc import AnyLoc

    spec = tiny("dinov2_vits14", monkeypatch)
    placed = weights_folder(tmp_path) / spec.file_name
    placed.parent.mkdir(parents=True)
    torch.manual_seed(0)
    torch.save(official_state_dict(create_model(spec), spec), placed)
    by_name = AnyLoc(backbone=spec.name, layer=1, aggregation="vlad", cache_dir=tmp_path)
    given = AnyLoc(backbone=spec.name, layer=1, aggregation="vlad", weights=str(placed), cache_dir=tmp_path)
    digest = hashlib.sha256(placed.read_bytes()).hexdigest()
    assert by_name.vocabulary_backbone == given.vocabulary_backbone == f"{spec.name}@{digest[:16]}"
    assert by_name.weights_identity() == given.weights_identity() == f"sha256:{digest}"
