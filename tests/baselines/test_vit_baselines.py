"""SALAD, BoQ and MegaLoc: exact checkpoint layouts, descriptors from reduced models, bad input.

The full-size architectures are only built on the meta device (no memory, no forward);
forwards run on depth-2 ViTs with few channels and small images.
"""
import json
import urllib.error
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import vprbench
from vprbench import VPRBenchError, create_method
from vprbench_baselines import boq, megaloc, salad
from vprbench.features.dense import interpolate_pos_embed
from vprbench.gemm import onednn_products
from vprbench_baselines.vit import ViTConfig

CHECKPOINTS = Path(__file__).resolve().parents[1] / "data" / "checkpoints"
TINY_VIT = ViTConfig(embed_dim=32, depth=2, heads=2)


def official_shapes(name: str) -> dict:
    """{parameter: shape} of the authors' model, dumped from their code with random weights."""
    return json.loads((CHECKPOINTS / f"{name}.json").read_text())


def shapes(model) -> dict:
    return {k: list(v.shape) for k, v in model.state_dict().items()}


def images(tmp_path, sizes=((70, 50), (64, 64), (90, 40))):
    rng = np.random.default_rng(0)
    paths = []
    for i, (w, h) in enumerate(sizes):
        path = tmp_path / f"img{i}.png"
        Image.fromarray(rng.integers(0, 256, (h, w, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return paths


def save_official(model, path, mask_token_prefix=None, wrap=False):
    """A checkpoint in the authors' layout (DINOv2's unused mask_token included where they have it)."""
    torch.manual_seed(1)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn_like(p) * 0.05)
    state = dict(model.state_dict())
    if mask_token_prefix is not None:
        state[f"{mask_token_prefix}mask_token"] = torch.zeros(1, TINY_VIT.embed_dim)
    torch.save({"state_dict": state} if wrap else state, path)
    return path


@pytest.fixture
def no_network(monkeypatch):
    def refuse(url, *args, **kwargs):
        raise urllib.error.URLError(f"no network in tests ({url})")

    monkeypatch.setattr(torch.hub, "download_url_to_file", refuse)


# ---------------------------------------------------------------- parameter layouts
@pytest.mark.parametrize(
    "name, build, mask_prefix",
    [
        ("salad", lambda: salad.Salad(), "backbone.model."),
        ("boq-dinov2", lambda: boq.BoQ(boq.RELEASED["dinov2", 12288]), "backbone.dino."),
        ("boq-resnet50", lambda: boq.BoQ(boq.RELEASED["resnet50", 16384]), None),
        ("megaloc", lambda: megaloc.MegaLoc(), None),
    ],
)
def test_released_checkpoint_layout_matches_exactly(name, build, mask_prefix):
    expected = official_shapes(name)
    if mask_prefix is not None:  # the only official key the model does not hold, and it is unused
        assert expected.pop(f"{mask_prefix}mask_token") == [1, 768]
    with torch.device("meta"):
        model = build()
    assert shapes(model) == expected


def test_released_dimensions():
    assert salad.SaladConfig().dim == 8448
    assert megaloc.MegaLocConfig().dim == 8448
    assert {key: cfg.dim for key, cfg in boq.RELEASED.items()} == {("resnet50", 16384): 16384, ("dinov2", 12288): 12288}
    assert boq.RELEASED["dinov2", 12288].resize == (322, 322)
    assert boq.RELEASED["resnet50", 16384].resize == (384, 384)


# ---------------------------------------------------------------- position embeddings
def test_pos_embed_interpolation_follows_official_scale_factor():
    torch.manual_seed(0)
    pos = torch.randn(1, 1 + 37 * 37, 8)
    assert interpolate_pos_embed(pos, (37, 37)) is pos
    out = interpolate_pos_embed(pos, (23, 23))
    assert out.shape == (1, 1 + 23 * 23, 8)
    assert torch.equal(out[:, 0], pos[:, 0])
    grid = pos[:, 1:].reshape(1, 37, 37, 8).permute(0, 3, 1, 2)
    plain = torch.nn.functional.interpolate(grid, size=(23, 23), mode="bicubic").permute(0, 2, 3, 1).reshape(1, -1, 8)
    assert (out[:, 1:] - plain).abs().max() > 1e-3  # the +0.1 offset moves the sampling grid


def test_trunk_tokens_equal_timms_forward_with_the_official_position_embedding():
    """vit_tokens (the one dense extractor) is timm's own forward pass once the position embedding
    is resampled the official way: bit for bit at the trained grid, and at a smaller one (timm's
    pass computing its linear layers as the extractor does, on oneDNN)."""
    from vprbench_baselines.vit import dinov2_vit, vit_tokens

    torch.manual_seed(0)
    trunk = dinov2_vit(TINY_VIT).eval()
    images = torch.randn(2, 3, 518, 518)
    with torch.no_grad(), onednn_products():
        assert torch.equal(vit_tokens(trunk, images, final_norm=True), trunk.forward_features(images))
        small = dinov2_vit(ViTConfig(embed_dim=32, depth=2, heads=2, img_size=224)).eval()
        state = trunk.state_dict()
        small.load_state_dict({**state, "pos_embed": interpolate_pos_embed(state["pos_embed"], (16, 16))})
        small.norm = torch.nn.Identity()  # the raw tokens (BoQ's input)
        images = images[..., :224, :224]
        assert torch.equal(vit_tokens(trunk, images, final_norm=False), small.forward_features(images))


# ---------------------------------------------------------------- reduced models end to end
def test_salad_descriptors_from_official_layout_file(tmp_path):
    config = salad.SaladConfig(vit=TINY_VIT, clusters=4, cluster_dim=8, token_dim=8)
    weights = save_official(salad.Salad(config), tmp_path / "dino_salad.ckpt", "backbone.model.")
    method = salad.build(config, weights=str(weights), resize=(56, 56), batch_size=2)
    paths = images(tmp_path)
    together = method.describe(paths)
    assert together.shape == (3, 4 * 8 + 8) and together.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(together, axis=1), 1.0, atol=1e-5)
    alone = np.concatenate([method.describe([p]) for p in paths])
    np.testing.assert_allclose(together, alone, atol=1e-5)
    # the same as the network on the authors' eval input: PIL bilinear resize, ToTensor, normalise
    import torchvision.transforms as T

    official = T.Compose([T.Resize((56, 56), interpolation=T.InterpolationMode.BILINEAR), T.ToTensor(),
                          T.Normalize(mean=[0.485, 0.456, 0.406], std=[0.229, 0.224, 0.225])])
    x = method.preprocess(paths[0]).unsqueeze(0)
    assert torch.equal(x[0], official(Image.open(paths[0]).convert("RGB")))
    with torch.no_grad():
        direct = method.model(x)[0].numpy()
    np.testing.assert_allclose(together[0], direct, atol=1e-5)
    fp = method.fingerprint()
    assert fp["dim"] == 40 and len(fp["weights_sha256"]) == 64 and fp["preprocess"]["resize"] == [56, 56]


def test_salad_aggregator_mass_and_layout():
    torch.manual_seed(0)
    scores = torch.randn(2, 4, 30)
    log_p = salad.sinkhorn_log_assignment(scores, torch.tensor(1.0))
    assert log_p.shape == (2, 5, 30)
    # each patch spreads (almost exactly, after 3 iterations) unit mass over clusters + dustbin
    np.testing.assert_allclose(log_p.exp().sum(dim=1).numpy(), 1.0, atol=1e-5)
    with pytest.raises(VPRBenchError, match="more patches"):
        salad.sinkhorn_log_assignment(torch.randn(1, 4, 4), torch.tensor(1.0))


@pytest.mark.parametrize("backbone", ["dinov2", "resnet50"])
def test_boq_descriptors_from_official_layout_file(tmp_path, backbone):
    config = boq.BoQConfig(backbone, 64, (56, 56), "tiny.pth", vit=TINY_VIT, queries=4, row_dim=2)
    prefix = "backbone.dino." if backbone == "dinov2" else None
    weights = save_official(boq.BoQ(config), tmp_path / "tiny.pth", prefix, wrap=backbone == "resnet50")
    method = boq.build(config, weights=str(weights))
    paths = images(tmp_path)[:2]
    out = method.describe(paths)
    assert out.shape == (2, 128)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(out[1:], method.describe(paths[1:]), atol=1e-5)
    assert method.preprocess.interpolation == "bicubic" and method.preprocess.resize == (56, 56)
    assert method.fingerprint()["dim"] == 128


def test_megaloc_full_resolution_rounds_to_patch_multiple(tmp_path):
    config = megaloc.MegaLocConfig(vit=TINY_VIT, clusters=4, cluster_dim=8, token_dim=8, hidden=16, dim=24)
    model = megaloc.MegaLoc(config)
    save_official(model, tmp_path / "w.pth")
    method = megaloc.build(config, weights=str(tmp_path / "w.pth"))
    paths = images(tmp_path)  # 70x50, 64x64, 90x40: none a multiple of 14 on both sides
    out = method.describe(paths)
    assert out.shape == (3, 24)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    x = method.preprocess(paths[0]).unsqueeze(0)
    assert x.shape == (1, 3, 50, 70)  # full resolution reaches the model, which resizes to 56x70
    resized = torch.nn.functional.interpolate(x, size=(56, 70), mode="bilinear", antialias=True)
    with torch.no_grad():
        np.testing.assert_allclose(model.eval()(resized)[0].numpy(), out[0], atol=1e-5)


def test_megaloc_reads_safetensors(tmp_path):
    from safetensors.torch import save_file

    config = megaloc.MegaLocConfig(vit=TINY_VIT, clusters=4, cluster_dim=8, token_dim=8, hidden=16, dim=24)
    model = megaloc.MegaLoc(config)
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(tmp_path / "model.safetensors"))
    method = megaloc.build(config, weights=str(tmp_path / "model.safetensors"))
    assert method.fingerprint()["weights_sha256"]
    (tmp_path / "bad.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(VPRBenchError, match="Cannot read checkpoint .*bad.safetensors"):
        megaloc.build(config, weights=str(tmp_path / "bad.safetensors"))


# ---------------------------------------------------------------- bad input
def test_checkpoint_mismatch_names_the_keys(tmp_path):
    config = salad.SaladConfig(vit=TINY_VIT, clusters=4, cluster_dim=8, token_dim=8)
    state = salad.Salad(config).state_dict()
    del state["aggregator.dust_bin"]
    state["aggregator.extra.weight"] = torch.zeros(2)
    state["aggregator.score.3.weight"] = torch.zeros(5, 512, 1, 1)
    torch.save(state, tmp_path / "bad.ckpt")
    with pytest.raises(VPRBenchError) as info:
        salad.build(config, weights=str(tmp_path / "bad.ckpt"), resize=(56, 56))
    message = str(info.value)
    assert "missing: aggregator.dust_bin" in message
    assert "unexpected: aggregator.extra.weight" in message
    assert "aggregator.score.3.weight (5, 512, 1, 1) (expected (4, 512, 1, 1))" in message


@pytest.mark.parametrize(
    "name, options, pattern",
    [
        ("boq-dinov2", {"dim": 16384}, r"no released model for backbone dinov2 with dimension 16384; valid: resnet50 -> 16384, dinov2 -> 12288"),
        ("boq-resnet50", {"backbone": "vgg16"}, r"unknown backbone 'vgg16'.*resnet50 -> 16384, dinov2 -> 12288"),
        ("boq-dinov2", {"dim": "many"}, r"dim must be an integer"),
        ("salad", {"backbone": "dinov2_vitl14"}, r"unknown backbone 'dinov2_vitl14'; valid: dinov2_vitb14"),
        ("salad", {"dim": "4096"}, r"dim 4096 is not available for dinov2_vitb14; valid: 8448"),
        ("salad", {"resize": (320, 320)}, r"not a multiple of the patch size 14"),
        ("megaloc", {"backbone": "resnet50"}, r"valid: dinov2_vitb14"),
        ("megaloc", {"dim": 1024}, r"dim 1024 is not available for dinov2_vitb14; valid: 8448"),
        ("boq-dinov2", {"layer": 3}, r"does not take option\(s\) layer"),
    ],
)
def test_invalid_options_list_valid_ones(name, options, pattern, no_network):
    with pytest.raises(VPRBenchError, match=pattern):
        create_method(name, **options)


@pytest.mark.parametrize(
    "name, file_name, url",
    [
        ("salad", "dino_salad.ckpt", "https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt"),
        ("boq-dinov2", "dinov2_12288.pth", "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/dinov2_12288.pth"),
        ("boq-resnet50", "resnet50_16384.pth", "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/resnet50_16384.pth"),
        ("megaloc", "model.safetensors", "https://huggingface.co/gberton/MegaLoc/resolve/main/model.safetensors"),
    ],
)
def test_offline_without_weights_says_how_to_supply_them(name, file_name, url, no_network):
    with pytest.raises(VPRBenchError) as info:
        create_method(name, device="cpu")
    message = str(info.value)
    assert "--weights PATH" in message and file_name in message and url in message
    assert "no network in tests" in message


def test_missing_local_weights_file(tmp_path):
    with pytest.raises(VPRBenchError, match=r"weights file .*nowhere.ckpt does not exist; download dino_salad.ckpt"):
        create_method("salad", weights=str(tmp_path / "nowhere.ckpt"))


def test_registered_through_entry_points_only():
    methods = vprbench.available_methods()
    for name in ("salad", "boq-dinov2", "boq-resnet50", "megaloc", "clip-cls"):
        assert methods[name].source == "vprbench_baselines"
    core = Path(vprbench.__file__).parent
    text = " ".join(p.read_text().lower() for p in core.rglob("*.py"))
    for word in ("salad", "megaloc", "boq", "vprbench_baselines"):
        assert word not in text


@pytest.mark.parametrize("backbone", ["dinov2", "resnet50"])
def test_boq_resize_native_is_the_image_as_stored_or_refused(tmp_path, backbone):
    """Before: `resize=native` ran at the authors' size while its row said 'native'."""
    config = boq.BoQConfig(backbone, 64, (56, 56), "tiny.pth", vit=TINY_VIT, queries=4, row_dim=2)
    prefix = "backbone.dino." if backbone == "dinov2" else None
    weights = save_official(boq.BoQ(config), tmp_path / "tiny.pth", prefix, wrap=backbone == "resnet50")
    if backbone == "dinov2":
        with pytest.raises(VPRBenchError, match=r"boq: the DINOv2 backbone takes sides that are multiples of 14, not "
                                                r"images as stored: give --resize H W \(the authors': 56 56\)"):
            boq.build(config, weights=str(weights), resize="native")
    else:
        assert boq.build(config, weights=str(weights), resize="native").preprocess.resize is None


@pytest.mark.parametrize("method", ["cosplace", "eigenplaces", "megaloc", "clip-cls"])
def test_resize_native_written_out_is_the_run_left_unset(method):
    """Before: these run on images as stored when resize is unset, yet `--resize native` made a second row
    (and run key) of the same numbers."""
    from vprbench.spec import resolve_spec

    native, unset = resolve_spec(method, "corridor", options={"resize": "native"}), resolve_spec(method, "corridor")
    assert (native.key, native.row_key, native.given) == (unset.key, unset.row_key, unset.given)
    assert resolve_spec(method, "corridor", options={"resize": [224, 224]}).key != unset.key


def test_netvlad_vgg16s_unset_resize_written_out_is_the_same_run():
    """Before: `--resize 480 640` on the WPCA models (their default) and `resize=native` on the 32768-d one
    (full resolution by default) each made a second row of the same numbers."""
    from vprbench.spec import resolve_spec

    def key(**options):
        return resolve_spec("netvlad-vgg16", "corridor", options=options).key

    assert key(resize=[480, 640]) == key() != key(resize="native")
    assert key(dim=32768, resize="native") == key(dim=32768) != key(dim=32768, resize=[480, 640])
