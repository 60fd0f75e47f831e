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


TINY = {"depth": 3, "embed_dim": 64, "num_heads": 2}


@pytest.mark.parametrize("name", ["dinov3_vits16", "pe_spatial_s16", "radio_v3_b16", "siglip2_b16",
                                  "dinov2_vits14_reg"])
def test_dense_features_of_every_new_family(name):
    """Shapes, every prefix token dropped, and q/k/v equal to a manual computation from the block's
    input (RoPE applied to the query and key of patch tokens where the family has it)."""
    from timm.layers import apply_rot_embed_cat

    from vprbench.features.dense import DenseExtractor

    spec = backbone_spec(name)
    torch.manual_seed(0)
    model = create_model(spec, **TINY)
    images = torch.randn(2, 3, 2 * spec.patch, 3 * spec.patch)
    seen = {}
    hook = model.blocks[1].attn.register_forward_pre_hook(
        lambda attn, args, kwargs: seen.update(x=args[0], rope=kwargs.get("rope")), with_kwargs=True)
    with torch.no_grad():
        tokens = DenseExtractor(model, spec, 1, "token")(images)
    hook.remove()
    assert tokens.shape == (2, 6, 64)
    x, rope = seen["x"], seen["rope"]
    assert x.shape[1] == 6 + spec.prefix_tokens
    assert (rope is not None) == (spec.position == "rope")
    attn = model.blocks[1].attn
    bias = torch.cat((attn.q_bias, attn.k_bias, attn.v_bias)) if getattr(attn, "q_bias", None) is not None \
        else attn.qkv.bias
    q, k, v = torch.nn.functional.linear(x, attn.qkv.weight, bias).reshape(2, x.shape[1], 3, 2, 32).unbind(2)
    q, k, v = (t[:, spec.prefix_tokens:] for t in (q, k, v))  # (B, patches, heads, head_dim)
    if rope is not None:
        half = getattr(attn, "rotate_half", False)  # DINOv3 rotates half-split pairs
        q, k = (apply_rot_embed_cat(t.transpose(1, 2), rope, half=half).transpose(1, 2) for t in (q, k))
    for facet, manual in (("query", q), ("key", k), ("value", v)):
        with torch.no_grad():
            got = DenseExtractor(model, spec, 1, facet)(images)
        assert got.shape == (2, 6, 64)
        torch.testing.assert_close(got, manual.reshape(2, 6, 64), rtol=0, atol=1e-5)
    if spec.position_interpolation == "timm":  # the official DINO path floors to whole patches, as the release
        with pytest.raises(VPRBenchError, match="not a multiple of the patch"):
                DenseExtractor(model, spec, 1, "value")(torch.randn(1, 3, spec.patch + 1, spec.patch))
    with pytest.raises(VPRBenchError, match="Layer 3 is out of range"):
        DenseExtractor(model, spec, 3, "value")


def test_anyloc_on_a_new_backbone_records_it_and_refuses_a_missing_cls(shared_data):
    from vprbench import create_method

    images = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:2]
    method = create_method("anyloc", backbone="dinov3_vits16", weights="random", layer=1, aggregation="gem",
                           resize="64x64")
    assert method.describe(images).shape == (2, 384)
    assert method.provenance()["weights"] == {"source": "random"}
    assert method.provenance()["backbone"] == {"name": "dinov3_vits16", "family": "DINOv3",
                                               "timm": "vit_small_patch16_dinov3.lvd1689m", "licence": "DINOv3 License",
                                               "gated": True, "access": "https://github.com/facebookresearch/dinov3"}
    with pytest.raises(VPRBenchError, match="backbone siglip2_b16 has no CLS token"):
        create_method("anyloc", backbone="siglip2_b16", weights="random", aggregation="cls")


def _pe_release(state):
    """timm's PE keys -> the perception_models release's (conv1, class_embedding, positional_embedding,
    transformer.resblocks.N.{ln_1,attn.in_proj_*,attn.out_proj,ln_2,mlp.c_fc,mlp.c_proj}), shapes as released."""
    swaps = [("patch_embed.proj", "conv1"), ("pos_embed", "positional_embedding"), ("blocks.", "transformer.resblocks."),
             ("norm_pre", "ln_pre"), (".norm1.", ".ln_1."), (".norm2.", ".ln_2."), ("attn.qkv.", "attn.in_proj_"),
             ("attn.proj", "attn.out_proj"), ("mlp.fc1", "mlp.c_fc"), ("mlp.fc2", "mlp.c_proj")]
    out = {}
    for key, value in state.items():
        if key == "cls_token":
            out["class_embedding"] = value.reshape(-1)
            continue
        for timm_part, release_part in swaps:
            key = key.replace(timm_part, release_part)
        out[key] = value[0] if key == "positional_embedding" else value
    return out


def _radio_release(state):
    """timm's RADIO keys -> the C-RADIO checkpoint's ({"state_dict": radio_model.model.*}: a bias-free
    patch_generator.embedder linear, one cls_token.token holding CLS and registers, blocks as timm)."""
    p = "radio_model.model."
    out = {f"{p}patch_generator.embedder.weight": state["patch_embed.proj.weight"].flatten(1),
           f"{p}patch_generator.pos_embed": state["pos_embed"],
           f"{p}patch_generator.cls_token.token": torch.cat([state["cls_token"][0], state["reg_token"][0]]),
           "radio_model.input_conditioner.norm_mean": torch.zeros(3, 1, 1)}  # dropped by the converter
    out.update({p + k.replace(".gamma", ".grandma"): v for k, v in state.items() if k.startswith("blocks.")})
    return {"state_dict": out, "args": {"model": "vit_base_patch16_224"}}


@pytest.mark.parametrize("name, release", [("pe_spatial_s16", _pe_release), ("radio_v3_b16", _radio_release)])
def test_release_format_file_of_a_new_family_loads_exactly(name, release, tmp_path):
    """A random tiny model written with the release's own key names and shapes, read back through
    the loader's file reader and converter: every tensor equal, nothing missing or left over."""
    from vprbench.features.backbones import read_checkpoint

    spec = backbone_spec(name)
    torch.manual_seed(0)
    model = create_model(spec, **TINY)
    if "patch_embed.proj.bias" in model.state_dict():
        torch.nn.init.zeros_(model.patch_embed.proj.bias)  # RADIO's patch embedding has no bias
    path = tmp_path / "release.pth"
    torch.save(release(model.state_dict()), path)
    converted = convert_official(read_checkpoint(path), create_model(spec, empty=True, **TINY))
    assert set(converted) == set(model.state_dict())
    for key, value in model.state_dict().items():
        assert torch.equal(converted[key], value), key
    wrong = create_model(backbone_spec("dinov3_vits16"), empty=True, **TINY)
    with pytest.raises(VPRBenchError, match="does not fit this backbone"):
        convert_official(read_checkpoint(path), wrong)


def test_a_facet_the_attention_cannot_give_is_refused_naming_both(monkeypatch):
    from vprbench import create_method

    entry = backbone_spec("siglip2_b16").model_copy(update={"name": "tokens_only", "facets": ("token",)})
    monkeypatch.setitem(backbones(), "tokens_only", entry)
    with pytest.raises(VPRBenchError, match=r"facet=value: backbone tokens_only gives token only"):
        create_method("anyloc", backbone="tokens_only", facet="value", weights="random", aggregation="gem")
    assert create_method("anyloc", backbone="tokens_only", facet="token", weights="random", aggregation="gem",
                         layer=3).facet == "token"
