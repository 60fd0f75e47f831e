"""Hub weights are looked up as timm looks them up (timm.models._hub.load_state_dict_from_hf): the
.safetensors first, then the file timm names (pytorch_model.bin unless the config names another)."""
import pytest
import torch

from vprbench.features.backbones import create_model, load_backbone
from vprbench.features.catalogue import backbone_spec, backbones
from vprbench.weights import hub_folder, record_download

COMMIT = "0" * 40


@pytest.fixture
def tiny_hub_entry(monkeypatch):
    """DINOv3 ViT-S (a timm hub repository) at a tiny size, listed as tiny-hub."""
    size = {"depth": 2, "embed_dim": 96, "num_heads": 2}
    entry = backbone_spec("dinov3_vits16")
    entry = entry.model_copy(update={"name": "tiny-hub", "depth": 2, "width": 96,
                                     "timm_kwargs": {**entry.timm_kwargs, **size}})
    monkeypatch.setitem(backbones(), entry.name, entry)
    torch.manual_seed(0)
    return entry, create_model(entry)


def test_hub_order_is_timms():
    entry = backbone_spec("dinov3_vits16")
    assert entry.hub_files == ("model.safetensors", "pytorch_model.bin")
    assert entry.model_copy(update={"hub_file": "open_clip_pytorch_model.bin"}).hub_files == \
        ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")
    assert entry.model_copy(update={"hub_file": "w.safetensors"}).hub_files == ("w.safetensors",)


def test_a_cached_hub_repository_with_pytorch_model_bin_only_loads_offline(tiny_hub_entry, tmp_path, monkeypatch):
    """The hub cache's own layout (refs/main naming a snapshot), offline: the .bin timm would load is found."""
    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf-home"))  # nothing outside tmp_path is read
    entry, model = tiny_hub_entry
    repo = hub_folder(tmp_path / "cache") / f"models--{entry.hub.replace('/', '--')}"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(COMMIT)
    (repo / "snapshots" / COMMIT).mkdir(parents=True)
    torch.save(model.state_dict(), repo / "snapshots" / COMMIT / "pytorch_model.bin")
    # as vprbench's download leaves it: with the record of the download of these bytes (without it, a
    # file put in the hub cache by hand, it is the user's file)
    record_download(entry.source, repo / "snapshots" / COMMIT / "pytorch_model.bin", "test", tmp_path / "cache")
    loaded, _, identity = load_backbone(entry.name, None, cache_dir=tmp_path / "cache")
    assert identity == f"hf:{entry.hub}/model.safetensors"  # the repository's weights, named as before
    for key, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key


def test_a_hub_repository_without_safetensors_downloads_the_bin(tiny_hub_entry, tmp_path, monkeypatch):
    import huggingface_hub
    from huggingface_hub.errors import RemoteEntryNotFoundError

    entry, model = tiny_hub_entry
    asked = []

    def metadata(url, **kwargs):
        asked.append(url.rsplit("/", 1)[-1])
        if url.endswith("model.safetensors"):
            error = RemoteEntryNotFoundError.__new__(RemoteEntryNotFoundError)  # the hub's 404, without a response
            Exception.__init__(error, "404: no such file")
            raise error

    def download(repo_id, filename, cache_dir=None, **kwargs):
        asked.append(("download", filename))
        path = tmp_path / "downloaded" / filename
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(model.state_dict(), path)
        return str(path)

    monkeypatch.setattr(huggingface_hub, "get_hf_file_metadata", metadata)
    monkeypatch.setattr(huggingface_hub, "hf_hub_download", download)
    loaded, _, _ = load_backbone(entry.name, None, cache_dir=tmp_path / "cache")
    assert asked == ["model.safetensors", "pytorch_model.bin", ("download", "pytorch_model.bin")]
    assert torch.equal(loaded.state_dict()["blocks.1.mlp.fc2.weight"], model.state_dict()["blocks.1.mlp.fc2.weight"])
