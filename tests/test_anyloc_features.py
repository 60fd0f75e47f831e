"""AnyLoc feature side: weights loading, preprocessing, pos-embed interpolation, dense facets."""
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vprbench import VPRBenchError
from vprbench.features.backbones import backbone_spec, create_model, load_backbone
from release_formats import official_state_dict
from vprbench.features.dense import DenseExtractor, interpolate_pos_embed
from vprbench.features.preprocess import crop_offsets, resize_tensor
from vprbench.features.resize import dataset_resize, parse_size


@pytest.fixture(scope="module")
def vits14_file(tmp_path_factory):
    """A random ViT-S/14 saved in the official dinov2 checkpoint format."""
    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    model = create_model(spec)
    path = tmp_path_factory.mktemp("w") / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(model, spec), path)
    return path, model


def test_official_checkpoint_round_trips(vits14_file):
    path, model = vits14_file
    raw = torch.load(path, weights_only=True)
    assert "mask_token" in raw and "blocks.0.ls1.gamma" in raw and raw["pos_embed"].shape == (1, 1370, 384)
    loaded, spec, identity = load_backbone("dinov2_vits14", path)
    assert identity.startswith("sha256:") and len(identity) == 7 + 64
    for k, v in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[k], v), k


def test_wrong_architecture_names_keys(tmp_path, vits14_file):
    path, _ = vits14_file
    with pytest.raises(VPRBenchError) as error:
        load_backbone("dinov2_vitb14", path)  # same keys, other widths
    assert "Shape mismatches" in str(error.value) and "pos_embed: file (1, 1370, 384) vs model (1, 1370, 768)" in str(error.value)
    with pytest.raises(VPRBenchError) as error:
        load_backbone("dino_vits8", path)  # DINOv2 file for DINO v1
    message = str(error.value)
    assert "Unexpected keys: blocks.0.ls1.gamma" in message
    state = torch.load(path, weights_only=True)
    del state["norm.weight"]
    partial = tmp_path / "partial.pth"
    torch.save(state, partial)
    with pytest.raises(VPRBenchError, match="Missing keys: norm.weight"):
        load_backbone("dinov2_vits14", partial)


def test_missing_weights_offline_says_how_to_supply(tmp_path, monkeypatch):
    def offline(*args, **kwargs):
        raise OSError("network unreachable")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    with pytest.raises(VPRBenchError) as error:
        load_backbone("dinov2_vitg14", cache_dir=tmp_path)
    message = str(error.value)
    assert "--weights" in message and "dinov2_vitg14_pretrain.pth" in message
    assert "https://dl.fbaipublicfiles.com/dinov2/dinov2_vitg14/dinov2_vitg14_pretrain.pth" in message
    with pytest.raises(VPRBenchError, match="does not exist"):
        load_backbone("dino_vits8", tmp_path / "nope.pth")
    with pytest.raises(VPRBenchError, match="Did you mean: .*dinov2_vits14"):
        backbone_spec("dinov2_vits16")


def test_downloaded_file_is_kept_in_the_cache_folder_given(tmp_path, monkeypatch, vits14_file):
    calls = []

    def fake_download(url, destination, hash_prefix=None, progress=True):
        calls.append(url)
        Path(destination).write_bytes(vits14_file[0].read_bytes())

    monkeypatch.setattr(torch.hub, "download_url_to_file", fake_download)
    _, _, identity = load_backbone("dinov2_vits14", cache_dir=tmp_path / "cache")
    _, _, again = load_backbone("dinov2_vits14", cache_dir=tmp_path / "cache")
    assert identity == again == backbone_spec("dinov2_vits14").url and len(calls) == 1
    assert (tmp_path / "cache" / "torch" / "hub" / "checkpoints" / "dinov2_vits14_pretrain.pth").is_file()


def test_crop_offsets_round_half_to_even():
    assert crop_offsets(227, 300, 14) == (2, 3, 224, 294)  # round(1.5) = 2: the crop starts at row 2
    assert crop_offsets(225, 14, 14) == (0, 0, 224, 14)    # 1/2 rounds to even 0
    assert crop_offsets(480, 640, 14) == (2, 5, 476, 630)
    with pytest.raises(VPRBenchError, match="smaller than one 14x14 patch"):
        crop_offsets(13, 100, 14)


def test_resize_policy_and_parsing():
    assert dataset_resize("pitts30k") == (480, 640) and dataset_resize("Baidu") == (480, 640)
    assert dataset_resize("mid-atlantic-ridge") == (405, 720) and dataset_resize("oxford") is None
    assert parse_size("480x640") == (480, 640) and parse_size((2, 3)) == (2, 3) and parse_size("native") is None
    assert parse_size(" 480 x 640 ") == (480, 640) and parse_size("32") == (32, 32)
    for text in ("big", "10x", "x10", "10,,10"):  # a missing side was read as a square
        with pytest.raises(VPRBenchError, match="HEIGHT WIDTH"):
            parse_size(text)


def test_resize_has_no_antialias():
    x = torch.arange(16.0).reshape(1, 4, 4).repeat(3, 1, 1)
    out = resize_tensor(x, (2, 2))
    # bilinear without antialias samples the centres of 2x2 blocks: mean of the 4 pixels
    assert torch.allclose(out[0], torch.tensor([[2.5, 4.5], [10.5, 12.5]]))


def test_pos_embed_interpolation_hand_case():
    # a 2x2 grid resampled to 1x3: scale (1.1/2, 3.1/2); bicubic a=-0.75, align_corners=False
    pos = torch.tensor([[[9.0], [0.0], [1.0], [2.0], [3.0]]])  # cls + 2x2 grid
    out = interpolate_pos_embed(pos, (1, 3))
    assert out.shape == (1, 4, 1) and out[0, 0, 0] == 9.0
    ref = F.interpolate(pos[:, 1:].reshape(1, 2, 2, 1).permute(0, 3, 1, 2), scale_factor=(1.1 / 2, 3.1 / 2),
                        mode="bicubic", align_corners=False)
    assert torch.equal(out[0, 1:, 0], ref.flatten())
    # the scale drives the sampling, not the size ratio: differs from size=(1, 3)
    by_size = F.interpolate(pos[:, 1:].reshape(1, 2, 2, 1).permute(0, 3, 1, 2), size=(1, 3), mode="bicubic")
    assert not torch.allclose(ref, by_size)
    assert torch.allclose(out[0, 1:, 0], torch.tensor(_bicubic_by_hand([[0.0, 1.0], [2.0, 3.0]], (1, 3))), atol=1e-6)
    assert torch.equal(interpolate_pos_embed(pos, (2, 2)), pos)  # trained grid: unchanged


def _bicubic_by_hand(grid, out_size, a=-0.75):
    """Separable cubic convolution, source = (dst + 0.5) / scale - 0.5, edge indices clamped."""
    def weights(t):
        def w(x):
            x = abs(x)
            return (a + 2) * x**3 - (a + 3) * x**2 + 1 if x <= 1 else a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a
        return [w(t + 1), w(t), w(1 - t), w(2 - t)]

    def axis(n_in, n_out):
        scale = (n_out + 0.1) / n_in
        rows = []
        for d in range(n_out):
            src = (d + 0.5) / scale - 0.5
            i0 = int(np.floor(src))
            row = [0.0] * n_in
            for k, wk in zip(range(i0 - 1, i0 + 3), weights(src - i0)):
                row[min(max(k, 0), n_in - 1)] += wk
            rows.append(row)
        return np.array(rows)

    g = np.array(grid)
    return (axis(g.shape[0], out_size[0]) @ g @ axis(g.shape[1], out_size[1]).T).flatten().tolist()


@pytest.fixture(scope="module")
def tiny_dinov2():
    torch.manual_seed(1)
    spec = backbone_spec("dinov2_vits14")
    return create_model(spec), spec


def test_facets_are_qkv_thirds_and_stop_after_block(tiny_dinov2):
    model, spec = tiny_dinov2
    x = torch.randn(2, 3, 56, 70)
    ran = []
    hooks = [b.register_forward_hook(lambda *a, i=i: ran.append(i)) for i, b in enumerate(model.blocks)]
    try:
        captured = {}
        h = model.blocks[2].attn.qkv.register_forward_hook(lambda m, i, o: captured.setdefault("qkv", o))
        feats = {f: DenseExtractor(model, spec, 2, f)(x) for f in ("query", "key", "value")}
        h.remove()
        assert ran == [0, 1] * 3  # block 2 is entered but stopped at its qkv; later blocks never run
        qkv = captured["qkv"][:, 1:]
        for i, f in enumerate(("query", "key", "value")):
            assert feats[f].shape == (2, 20, 384)
            assert torch.equal(feats[f], qkv[..., i * 384:(i + 1) * 384])
        ran.clear()
        token = DenseExtractor(model, spec, 2, "token")(x)
        assert ran == [0, 1, 2] and token.shape == (2, 20, 384)
    finally:
        for h in hooks:
            h.remove()


def test_token_facet_matches_timm_at_native_grid(tiny_dinov2):
    model, spec = tiny_dinov2
    x = torch.randn(1, 3, 518, 518)  # 37x37: timm needs no resampling, so both paths must agree
    ours = DenseExtractor(model, spec, 0, "token")(x)
    with torch.no_grad():
        ref = model.blocks[0](model._pos_embed(model.patch_embed(x)))
    assert torch.allclose(ours, ref[:, 1:], atol=1e-5)


def test_layer_and_facet_errors(tiny_dinov2):
    model, spec = tiny_dinov2
    with pytest.raises(VPRBenchError, match=r"valid layers are 0\.\.11"):
        DenseExtractor(model, spec, 12, "value")
    with pytest.raises(VPRBenchError, match="query, key, value, token"):
        DenseExtractor(model, spec, 3, "values")


def test_dino_v1_interleaved_heads_and_stride():
    torch.manual_seed(2)
    spec = backbone_spec("dino_vits8")
    model = create_model(spec)
    ext = DenseExtractor(model, spec, 1, "key", stride=4, head_interleaved=True)
    x = torch.randn(1, 3, 24, 32)
    assert ext.grid(24, 32) == (5, 7)
    captured = {}
    h = model.blocks[1].attn.qkv.register_forward_hook(lambda m, i, o: captured.setdefault("qkv", o))
    out = ext(x)
    h.remove()
    k = captured["qkv"][0, 1:, 384:768]  # natural order: head h, dim j at h*64 + j
    assert out.shape == (1, 35, 384)
    assert torch.equal(out[0, :, 5 * 6 + 2], k[:, 2 * 64 + 5])  # channel j*heads + h for j=5, h=2
