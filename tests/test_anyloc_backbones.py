"""Backbones as data: every manifest entry matches its timm architecture; official-format files
of the new families load; timm:ARCH.TAG works for ViTs and is refused for models without patches."""
import pytest
import torch

from vprbench import VPRBenchError
from vprbench.features.backbones import convert_official, create_model, official_state_dict
from vprbench.features.catalogue import _entries, backbone_spec, backbones


@pytest.mark.parametrize("name", sorted(backbones()))
def test_entry_matches_its_timm_architecture(name):
    spec = backbone_spec(name)
    model = create_model(spec, empty=True)
    assert (len(model.blocks), model.embed_dim) == (spec.depth, spec.width)
    assert model.patch_embed.patch_size[0] == spec.patch
    assert getattr(model, "num_prefix_tokens", 1) == spec.prefix_tokens
    assert (getattr(model, "rope", None) is not None) == (spec.position == "rope")
    assert spec.source.where.startswith("https://")


@pytest.mark.parametrize("name", ["dinov2_vitg14", "dinov2_vits14_reg", "dinov3_vits16", "dino_vits8"])
def test_official_format_file_of_a_tiny_model_loads_exactly(name):
    spec = backbone_spec(name)
    torch.manual_seed(0)
    tiny = dict(depth=2, embed_dim=96, num_heads=2)  # 96: the SwiGLU hidden width stays even
    model = create_model(spec, **tiny)
    official = official_state_dict(model, spec)
    for timm_part, official_part in spec.official_rename.items():
        assert not any(timm_part in k for k in official) and any(official_part in k for k in official)
    converted = convert_official(official, create_model(spec, empty=True, **tiny))
    assert set(converted) == set(model.state_dict())
    for key, value in model.state_dict().items():
        assert torch.equal(converted[key], value), key


def test_timm_names_any_vit_and_refuses_models_without_patch_tokens():
    spec = backbone_spec("timm:vit_small_patch16_dinov3.lvd1689m")
    assert (spec.patch, spec.prefix_tokens, spec.position, spec.depth) == (16, 5, "rope", 12)
    assert spec.source.hub == "timm/vit_small_patch16_dinov3.lvd1689m"
    with pytest.raises(VPRBenchError, match="timm:resnet50.a1_in1k has no patch tokens"):
        backbone_spec("timm:resnet50.a1_in1k")
    with pytest.raises(VPRBenchError, match="timm has no weights 'nope' for vit_small_patch16_dinov3; tags: lvd1689m"):
        backbone_spec("timm:vit_small_patch16_dinov3.nope")


def test_bad_manifest_entry_is_named():
    text = '[family]\nfamily = "X"\n[[backbone]]\nname = "x"\ntimm = "vit_small_patch16_224"\n'
    with pytest.raises(VPRBenchError, match=r"Backbone manifest bad.toml, entry 'x': patch: Field required"):
        _entries(text, "bad.toml")
