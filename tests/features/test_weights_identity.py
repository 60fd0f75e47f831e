"""One identity per weights: a release whose sha256 the manifest pins is named by it, downloaded or
as a local copy of the same bytes; records still name its URL and sha256."""
import shutil

import pytest
import torch

from release_formats import write_release
from vprbench.features.backbones import create_model, load_backbone, weights_identity
from vprbench.features.catalogue import backbone_spec, backbones
from vprbench.methods.anyloc import AnyLoc
from vprbench.weights import file_sha256, weights_provenance


@pytest.fixture
def pinned(tmp_path, monkeypatch):
    """A tiny DINOv2 written in the release's format, listed with the file's sha256 pinned (in capitals,
    as a manifest may write it), and a fake download that copies that file (never the network)."""
    size = {"depth": 2, "embed_dim": 96, "num_heads": 2}
    entry = backbone_spec("dinov2_vits14")
    entry = entry.model_copy(update={"name": "tiny-pinned", "depth": 2, "width": 96,
                                     "timm_kwargs": {**entry.timm_kwargs, **size}})
    torch.manual_seed(0)
    (tmp_path / "local").mkdir()
    path = write_release(create_model(entry), entry, tmp_path / "local")
    digest = file_sha256(path)
    entry = entry.model_copy(update={"sha256": digest.upper()})
    monkeypatch.setitem(backbones(), entry.name, entry)
    calls = []

    def download(url, destination, hash_prefix=None, progress=True):
        calls.append((url, hash_prefix))
        shutil.copyfile(path, destination)

    monkeypatch.setattr(torch.hub, "download_url_to_file", download)
    return entry, path, digest, calls


def test_download_and_local_copy_of_a_pinned_release_are_one_identity(pinned, tmp_path):
    entry, path, digest, calls = pinned
    assert weights_identity(entry, None) == weights_identity(entry, path) == f"sha256:{digest}"
    _, _, downloaded = load_backbone(entry.name, None, cache_dir=tmp_path / "cache")
    _, _, local = load_backbone(entry.name, path)
    assert downloaded == local == f"sha256:{digest}"
    assert calls == [(entry.url, digest)]  # torch checks the download against the pin, in lower case
    # the record names the release by its URL and sha256, whichever way the bytes came
    assert weights_provenance(local) == {"source": "official", "url": entry.url, "sha256": digest,
                                         "recognised_by": "sha256", "release": "dinov2"}
    methods = [AnyLoc(backbone=entry.name, weights=w, layer=1, aggregation="gem", cache_dir=tmp_path / "cache")
               for w in (None, str(path))]
    assert methods[0].fingerprint() == methods[1].fingerprint()
    assert methods[0].weights_provenance() == methods[1].weights_provenance() == weights_provenance(local)
    assert [m.vocabulary_backbone for m in methods] == [entry.name, entry.name]  # official: the release's centres
    other = tmp_path / "other.pth"  # other bytes stay the user's file
    torch.save(torch.load(path) | {"cls_token": torch.zeros(1, 1, 96)}, other)
    assert weights_provenance(weights_identity(entry, other)) == {"source": "user", "sha256": file_sha256(other)}
