"""Each baseline loads a random checkpoint in the authors' file layout through the real
`weights=PATH` path, describes images, and fails with clear messages on bad input."""
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import vprbench
from vprbench import VPRBenchError, create_method

@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(0)
    paths = []
    for i, size in enumerate([(64, 64), (64, 64), (48, 64)]):
        path = tmp_path / f"img{i}.png"
        Image.fromarray(rng.integers(0, 255, (*size, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


def check_descriptors(method, paths, dim, check_batch=True):
    out = method.describe(paths)
    assert out.shape == (len(paths), dim)
    assert out.dtype == np.float32
    assert np.isfinite(out).all()
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    if check_batch:  # a row never depends on its batch
        np.testing.assert_allclose(out[1:2], method.describe(paths[1:2]), atol=1e-5)
    return out


def assert_loaded(method, state):
    loaded = method.model.state_dict()
    for key in list(state)[:3] + list(state)[-3:]:
        assert torch.equal(loaded[key].float(), state[key].float()), key


def test_registered_through_entry_points_only():
    methods = vprbench.available_methods()
    for name in ["netvlad", "netvlad-vgg16", "cosplace", "eigenplaces", "mixvpr"]:
        assert methods[name].source == "vprbench_baselines"
    core = Path(vprbench.__file__).parent
    for source in core.rglob("*.py"):
        assert "vprbench_baselines" not in source.read_text(), source


def test_cosplace_loads_official_layout(tmp_path, images, official_checkpoint):
    state = official_checkpoint("cosplace", "ResNet18_512")
    path = tmp_path / "ResNet18_512_cosplace.pth"
    torch.save(state, path)  # the released files are plain state dicts
    method = create_method("cosplace", backbone="ResNet18", dim=512, weights=str(path), resize=(64, 64), device="cpu")
    assert_loaded(method, state)
    check_descriptors(method, images[:2], 512)
    fp = method.fingerprint()
    assert (fp["backbone"], fp["dim"], fp["preprocess"]["resize"]) == ("ResNet18", 512, [64, 64])
    assert len(fp["weights_sha256"]) == 64


@pytest.mark.parametrize("name, variant, resize", [("cosplace", "ResNet18_512", (32, 48)),
                                                   ("mixvpr", "resnet50_4096", (320, 320))])
def test_anyloc_preprocessing_resizes_the_normalised_tensor(tmp_path, images, official_checkpoint, name, variant,
                                                             resize):
    """preprocess=anyloc is AnyLoc's evaluation of these baselines: its loaders normalise, then resize the
    tensor bilinearly without antialiasing (torchvision 0.14); the default stays each authors' own."""
    import torch.nn.functional as F

    path = tmp_path / f"{name}.pth"
    torch.save(official_checkpoint(name, variant), path)
    extra = {"backbone": "ResNet18", "dim": 512, "resize": resize} if name == "cosplace" else {}
    method = create_method(name, weights=str(path), device="cpu", preprocess="anyloc", **extra)
    rgb = torch.from_numpy(np.asarray(Image.open(images[2]).convert("RGB"))).permute(2, 0, 1).float() / 255
    mean, std = torch.tensor([0.485, 0.456, 0.406]).view(3, 1, 1), torch.tensor([0.229, 0.224, 0.225]).view(3, 1, 1)
    wanted = F.interpolate(((rgb - mean) / std)[None], size=resize, mode="bilinear", align_corners=False,
                           antialias=False)[0]
    torch.testing.assert_close(method.preprocess(images[2]), wanted, atol=1e-5, rtol=0)
    authors = create_method(name, weights=str(path), device="cpu", **extra)
    assert authors.fingerprint()["preprocess"]["normalise_first"] is False
    assert method.fingerprint()["preprocess"]["antialias"] is False
    with pytest.raises(VPRBenchError, match="unknown preprocess 'vprbench'; valid: authors, anyloc"):
        create_method(name, weights=str(path), device="cpu", preprocess="vprbench", **extra)


def test_cosplace_other_release_from_minus_o_strings(tmp_path, images, official_checkpoint):
    state = official_checkpoint("cosplace", "ResNet18_512")
    state["aggregation.3.weight"] = state["aggregation.3.weight"][:128]
    state["aggregation.3.bias"] = state["aggregation.3.bias"][:128]
    path = tmp_path / "ResNet18_128_cosplace.pth"
    torch.save(state, path)
    method = create_method("cosplace", backbone="resnet18", dim="128", weights=str(path), device="cpu")
    out = check_descriptors(method, images, 128)  # full resolution: mixed sizes in one call
    assert method.fingerprint()["preprocess"]["resize"] is None
    assert out.shape == (3, 128)


def test_eigenplaces_loads_official_layout(tmp_path, images, official_checkpoint):
    state = official_checkpoint("eigenplaces", "ResNet18_512")
    path = tmp_path / "ResNet18_512_eigenplaces.pth"
    torch.save(state, path)
    method = create_method("eigenplaces", backbone="ResNet18", dim=512, weights=str(path), device="cpu")
    assert_loaded(method, state)
    check_descriptors(method, images, 512)
    assert method.fingerprint()["architecture"] == "eigenplaces"


def test_mixvpr_loads_official_layout_at_320(tmp_path, images, official_checkpoint):
    state = official_checkpoint("mixvpr", "resnet50_4096")
    path = tmp_path / "resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt"
    torch.save(state, path)
    method = create_method("mixvpr", weights=str(path), device="cpu")
    assert_loaded(method, state)
    check_descriptors(method, images[:2], 4096, check_batch=False)
    assert method.fingerprint()["preprocess"]["resize"] == [320, 320]
    assert method.fingerprint()["preprocess"]["interpolation"] == "bicubic"


def test_benchmark_netvlad_loads_training_checkpoint_with_dataparallel_prefix(tmp_path, images, official_checkpoint):
    state = official_checkpoint("netvlad-dvgl", "resnet18conv4_netvlad")
    path = tmp_path / "best_model.pth"
    torch.save({"epoch_num": 3, "model_state_dict": {f"module.{k}": v for k, v in state.items()}}, path)
    method = create_method("netvlad", weights=str(path), resize=(64, 64), device="cpu")
    assert_loaded(method, state)
    check_descriptors(method, images, 64 * 256)
    fp = method.fingerprint()
    assert (fp["backbone"], fp["training"], fp["preprocess"]["normalise_first"]) == ("resnet18conv4", "pitts30k", True)


def test_netvlad_vgg16_wpca_loads_patch_netvlad_checkpoint(tmp_path, images, official_checkpoint):
    state = official_checkpoint("netvlad-patchnetvlad", "vgg16_wpca128")
    path = tmp_path / "pitts_WPCA128.pth.tar"
    # Patch-NetVLAD files are training checkpoints holding numpy scalars beside the weights
    torch.save({"epoch": 1, "best_score": np.float64(0.9), "state_dict": state}, path)
    method = create_method("netvlad-vgg16", dim="128", weights=str(path), resize=(64, 64), device="cpu")
    assert_loaded(method, state)
    check_descriptors(method, images[:2], 128)


def test_netvlad_layer_matches_the_looped_reference():
    from vprbench_baselines.netvlad import NetVLAD

    torch.manual_seed(0)
    layer = NetVLAD(clusters=4, dim=6)
    x = torch.randn(2, 6, 3, 5)
    # the per-cluster loop of the public implementations, written out
    xn = torch.nn.functional.normalize(x, dim=1).flatten(2)
    assign = torch.softmax(layer.conv(torch.nn.functional.normalize(x, dim=1)).flatten(2), dim=1)
    vlad = torch.stack([((xn - layer.centroids[k][None, :, None]) * assign[:, k : k + 1]).sum(-1) for k in range(4)], 1)
    vlad = torch.nn.functional.normalize(torch.nn.functional.normalize(vlad, dim=2).flatten(1), dim=1)
    torch.testing.assert_close(layer(x), vlad, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------ bad input
def test_unknown_backbone_lists_released_pairs():
    with pytest.raises(VPRBenchError) as info:
        create_method("cosplace", backbone="resnet34", device="cpu")
    assert "resnet34" in str(info.value)
    assert "ResNet18: 32, 64, 128, 256, 512" in str(info.value)


def test_unreleased_dimension_lists_valid_ones():
    with pytest.raises(VPRBenchError) as info:
        create_method("eigenplaces", backbone="ResNet18", dim="1024", device="cpu")
    assert "ResNet18 comes in 256, 512" in str(info.value)
    with pytest.raises(VPRBenchError, match="valid: 4096, 512, 128"):
        create_method("mixvpr", dim=1024, device="cpu")
    with pytest.raises(VPRBenchError, match="valid: 4096, 512, 128, 32768"):
        create_method("netvlad-vgg16", dim=1000, device="cpu")
    with pytest.raises(VPRBenchError, match=r"resnet18conv4 \(16384-d\)"):
        create_method("netvlad", backbone="alexnet", device="cpu")


def test_mixvpr_rejects_a_resize_its_mixer_cannot_take():
    with pytest.raises(VPRBenchError, match="valid: 320 320"):
        create_method("mixvpr", resize=(224, 224), device="cpu")


def test_checkpoint_of_another_backbone_names_the_keys(tmp_path, official_checkpoint):
    path = tmp_path / "ResNet18_512_cosplace.pth"
    torch.save(official_checkpoint("cosplace", "ResNet18_512"), path)
    with pytest.raises(VPRBenchError) as info:
        create_method("cosplace", backbone="ResNet50", dim=2048, weights=str(path), device="cpu")
    message = str(info.value)
    assert "missing: backbone.4.0.conv3.weight" in message
    assert "wrong shape: backbone.4.0.conv1.weight (64, 64, 3, 3) (expected (64, 64, 1, 1))" in message


def test_offline_download_says_how_to_supply_weights(monkeypatch):
    def offline(*args, **kwargs):
        raise OSError("no network")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    with pytest.raises(VPRBenchError) as info:
        create_method("cosplace", device="cpu")
    message = str(info.value)
    assert "ResNet101_2048_cosplace.pth" in message
    assert "https://github.com/gmberton/CosPlace/releases/download/v1.0/ResNet101_2048_cosplace.pth" in message
    assert "--weights PATH" in message
    with pytest.raises(VPRBenchError, match=r"pitts_WPCA4096.pth.tar.*huggingface.co/TobiasRobotics"):
        create_method("netvlad-vgg16", device="cpu")


@pytest.mark.parametrize("name", ["netvlad", "mixvpr"])
def test_drive_only_weights_point_to_the_page(monkeypatch, name):
    monkeypatch.setattr(torch.hub, "download_url_to_file", lambda *a, **k: pytest.fail("must not download"))
    with pytest.raises(VPRBenchError) as info:
        create_method(name, device="cpu")
    assert "https://drive.google.com/file/d/" in str(info.value)
    assert "--weights PATH" in str(info.value)
