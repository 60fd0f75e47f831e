"""Weight resolution, exact loading and preprocessing shared by the baselines."""
import numpy as np
import pytest
import torch
from PIL import Image
from torch import nn

from vprbench import VPRBenchError
from vprbench_baselines import common


def _image(path, size=(40, 30), seed=0):
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 255, (size[1], size[0], 3), dtype=np.uint8)).save(path)
    return path


def test_as_resize_forms():
    assert common.as_resize("320x320") == (320, 320)
    assert common.as_resize("480,640") == (480, 640)
    assert common.as_resize((480, 640)) == (480, 640)
    assert common.as_resize(224) == (224, 224)
    assert common.as_resize(None) is None
    with pytest.raises(VPRBenchError, match="Option resize takes HEIGHT WIDTH"):
        common.as_resize((1, 2, 3))
    with pytest.raises(VPRBenchError, match="integer"):
        common.as_int("twelve", "dim")


def test_load_exact_names_missing_unexpected_and_shape():
    model = nn.Sequential(nn.Linear(4, 3), nn.Linear(3, 2))
    state = model.state_dict()
    state["extra.weight"] = torch.zeros(1)
    del state["1.bias"]
    state["0.weight"] = torch.zeros(5, 4)
    with pytest.raises(VPRBenchError) as info:
        common.load_exact(model, state, "toy")
    message = str(info.value)
    assert "missing: 1.bias" in message
    assert "unexpected: extra.weight" in message
    assert "0.weight (5, 4) (expected (3, 4))" in message


def test_state_dict_of_unwraps_training_checkpoints():
    inner = {"module.a": torch.ones(1), "module.b": torch.zeros(2)}
    assert set(common.state_dict_of({"model_state_dict": inner, "epoch": 3})) == {"a", "b"}
    assert set(common.state_dict_of({"state_dict": {"x": torch.ones(1)}})) == {"x"}
    with pytest.raises(VPRBenchError, match="not a state dict"):
        common.state_dict_of([1, 2])


def test_local_weights_identity_is_file_sha256(tmp_path):
    path = tmp_path / "w.pth"
    torch.save({"a": torch.arange(3)}, path)
    source = common.WeightSource("w.pth", url="https://example.org/w.pth")
    checkpoint, identity = common.load_checkpoint(str(path), source, "toy")
    assert torch.equal(checkpoint["a"], torch.arange(3))
    assert identity == {"weights_sha256": common.file_sha256(path)}
    assert len(identity["weights_sha256"]) == 64


def test_missing_local_file_says_how_to_get_it(tmp_path):
    source = common.WeightSource("w.pth", url="https://example.org/w.pth")
    with pytest.raises(VPRBenchError, match=r"does not exist; download w.pth from https://example.org/w.pth"):
        common.load_checkpoint(tmp_path / "nope.pth", source, "toy")


def test_offline_download_error_says_how_to_supply(monkeypatch):
    def offline(*args, **kwargs):
        raise OSError("network is unreachable")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    source = common.WeightSource("w.pth", url="https://example.org/w.pth")
    with pytest.raises(VPRBenchError) as info:
        common.load_checkpoint(None, source, "toy")
    assert "--weights PATH" in str(info.value)
    assert "https://example.org/w.pth" in str(info.value)


def test_drive_only_weights_need_a_local_file():
    source = common.WeightSource("m.ckpt", page="https://drive.example/m")
    with pytest.raises(VPRBenchError, match=r"m.ckpt only at https://drive.example/m.*--weights PATH"):
        common.load_checkpoint(None, source, "toy")


def test_downloaded_file_is_cached_in_the_cache_folder_given(monkeypatch, tmp_path):
    calls = []

    def fake_download(url, dst, hash_prefix=None, progress=True):
        calls.append((url, hash_prefix))
        torch.save({"a": torch.ones(2)}, dst)

    monkeypatch.setattr(torch.hub, "download_url_to_file", fake_download)
    source = common.WeightSource("w.pth", url="https://example.org/w.pth", sha256="ab" * 32)
    _, identity = common.load_checkpoint(None, source, "toy", tmp_path / "cache")
    common.load_checkpoint(None, source, "toy", tmp_path / "cache")  # second time from the cache
    assert calls == [("https://example.org/w.pth", "ab" * 32)]
    assert (tmp_path / "cache" / "torch" / "hub" / "checkpoints" / "w.pth").is_file()
    assert identity == {"weights_url": "https://example.org/w.pth", "weights_sha256": "ab" * 32}


def test_preprocess_resizes_and_normalises(tmp_path):
    path = _image(tmp_path / "a.png", size=(40, 30))
    fixed = common.Preprocess(resize=(16, 24))(path)
    assert fixed.shape == (3, 16, 24)
    shorter = common.Preprocess(resize=15)(path)
    assert shorter.shape == (3, 15, 20)
    full = common.Preprocess()(path)
    raw = torch.from_numpy(np.array(Image.open(path))).permute(2, 0, 1).float() / 255
    mean = torch.tensor(common.IMAGENET_MEAN)[:, None, None]
    std = torch.tensor(common.IMAGENET_STD)[:, None, None]
    assert torch.allclose(full, (raw - mean) / std, atol=1e-6)


class _MeanColour(nn.Module):
    def forward(self, x):
        return x.mean(dim=(2, 3)) + torch.tensor([1.0, 2.0, 3.0])


def test_torch_method_groups_sizes_and_is_batch_independent(tmp_path):
    paths = [_image(tmp_path / f"{i}.png", size=(20 + 4 * (i % 2), 16), seed=i) for i in range(5)]
    method = common.TorchMethod(_MeanColour(), common.Preprocess(), {"arch": "toy"}, batch_size=2, dim=3)
    together = method.describe(paths)
    alone = np.concatenate([method.describe([p]) for p in paths])
    assert together.shape == (5, 3) and together.dtype == np.float32
    np.testing.assert_allclose(together, alone, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(together, axis=1), 1.0, atol=1e-6)
    assert method.describe([]).shape == (0, 3)
    assert method.fingerprint()["preprocess"]["resize"] is None


def test_torch_method_rejects_bad_device_and_precision():
    with pytest.raises(VPRBenchError, match="precision"):
        common.TorchMethod(_MeanColour(), common.Preprocess(), {}, precision="fp8")
    with pytest.raises(VPRBenchError, match="device"):
        common.TorchMethod(_MeanColour(), common.Preprocess(), {}, device="tpu")


def test_training_checkpoint_with_numpy_scalars_loads_without_unpickling_code(tmp_path):
    path = tmp_path / "train.pth.tar"
    torch.save({"epoch": 3, "best_score": np.float64(0.8), "recalls": {1: np.float64(0.7)},
                "pca": np.zeros(2), "state_dict": {"w": torch.ones(2)}}, path)
    checkpoint, _ = common.load_checkpoint(path, common.WeightSource("train.pth.tar"), "toy")
    assert checkpoint["best_score"] == 0.8
    assert torch.equal(common.state_dict_of(checkpoint)["w"], torch.ones(2))


class _Opaque:
    pass


def test_checkpoint_with_python_objects_is_refused_with_a_way_out(tmp_path):
    path = tmp_path / "pickled.pth"
    torch.save({"state_dict": {"w": torch.ones(1)}, "args": _Opaque()}, path)
    with pytest.raises(VPRBenchError) as info:
        common.load_checkpoint(path, common.WeightSource("pickled.pth"), "toy")
    assert "_Opaque" in str(info.value)
    assert "save its weights alone" in str(info.value)


def test_truncated_checkpoint_is_named(tmp_path):
    path = tmp_path / "cut.pth"
    torch.save({"w": torch.ones(1000)}, path)
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(VPRBenchError, match="Cannot read checkpoint .*cut.pth"):
        common.load_checkpoint(path, common.WeightSource("cut.pth"), "toy")
