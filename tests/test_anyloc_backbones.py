"""Backbones as data: every manifest entry matches its timm architecture; official-format files
of the new families load; timm:ARCH.TAG works for ViTs and is refused for models without patches."""
import pytest
import torch

from vprbench import VPRBenchError
from vprbench.features.backbones import create_model, load_backbone
from vprbench.features.catalogue import BackboneEntry, _entries, backbone_spec, backbones
from vprbench.features.dense import DenseExtractor
from release_formats import official_state_dict, siglip2_npz, write_release


@pytest.mark.parametrize("name", sorted(backbones()))
def test_entry_matches_its_timm_architecture(name):
    spec = backbone_spec(name)
    model = create_model(spec, empty=True)
    assert (len(model.blocks), model.embed_dim) == (spec.depth, spec.width)
    assert (getattr(model, "patch_embed", None) or model.embeds).patch_size[0] == spec.patch
    assert getattr(model, "num_prefix_tokens", 1) == spec.prefix_tokens
    assert (getattr(model, "rope", None) is not None) == (spec.position == "rope")
    assert spec.source.where.startswith("https://")


def tiny(name: str, monkeypatch, **size) -> BackboneEntry:
    """The entry `name` at a tiny size (2 blocks of width 96; its own timm architecture), listed
    as `tiny-NAME` so the whole loader runs on it."""
    size = {"depth": 2, "embed_dim": 96, "num_heads": 2, **size}  # 96: a SwiGLU hidden width stays even
    entry = backbone_spec(name)
    entry = entry.model_copy(update={"name": f"tiny-{name}", "depth": size["depth"], "width": size["embed_dim"],
                                     "timm_kwargs": {**entry.timm_kwargs, **size}})
    monkeypatch.setitem(backbones(), entry.name, entry)
    return entry


RELEASES = ["dino_vits8", "dinov2_vits14", "dinov2_vitg14", "dinov2_vits14_reg", "dinov2_vitg14_reg", "dinov3_vits16",
            "dinov3_vitl16_sat", "pe_spatial_s16", "pe_core_s16", "radio_v3_b16", "siglip2_b16"]


@pytest.mark.parametrize("name", RELEASES)
def test_release_file_of_every_family_loads_exactly(name, tmp_path, monkeypatch):
    """A random model written with its release's own keys, shapes and layout (tests/release_formats.py),
    read through the loader: every tensor equal, no buffer left without storage, and the same
    features as the model it was written from."""
    spec = tiny(name, monkeypatch)
    torch.manual_seed(0)
    model = create_model(spec)
    path = write_release(model, spec, tmp_path)
    loaded, _, identity = load_backbone(spec.name, path)
    assert identity.startswith("sha256:")
    assert not any(t.is_meta for t in [*loaded.parameters(), *loaded.buffers()])
    expected = model.state_dict()
    assert set(loaded.state_dict()) == set(expected)
    for key, value in expected.items():
        assert torch.equal(loaded.state_dict()[key], value), key
    images = torch.randn(1, 3, 2 * spec.patch, 3 * spec.patch)
    for facet in ("token", "value"):
        assert torch.equal(DenseExtractor(loaded, spec, 1, facet)(images), DenseExtractor(model, spec, 1, facet)(images))


def test_dinov3_biases_that_add_something_are_refused(tmp_path, monkeypatch):
    """timm's DINOv3 has no q/k/v biases; the release's are zero (and k is masked): a file whose
    biases are not is refused rather than silently changed."""
    spec = tiny("dinov3_vits16", monkeypatch)
    model = create_model(spec)
    state = official_state_dict(model, spec)
    state["blocks.1.attn.qkv.bias"][96 + 3] = 0.5  # a key bias, masked out by the release's bias_mask
    torch.save(state, tmp_path / "masked.pth")
    load_backbone(spec.name, tmp_path / "masked.pth")
    state["blocks.1.attn.qkv.bias"][3] = 0.5  # a query bias
    torch.save(state, tmp_path / "biased.pth")
    with pytest.raises(VPRBenchError, match=r"non-zero attention biases \(blocks.1.attn.qkv.bias\)"):
        load_backbone(spec.name, tmp_path / "biased.pth")


def test_a_release_of_another_size_or_family_is_refused(tmp_path, monkeypatch):
    import numpy as np

    spec = tiny("siglip2_b16", monkeypatch)
    arrays = siglip2_npz(create_model(spec))
    wider = {k: np.repeat(v, 2, axis=1) if k.endswith("pos_embedding") else v for k, v in arrays.items()}
    np.savez(tmp_path / "grid.npz", **wider)  # 392 positions: another input size
    with pytest.raises(VPRBenchError, match=r"Shape mismatches: pos_embed: file \(1, 392, 96\) vs model \(1, 196, 96\)"):
        load_backbone(spec.name, tmp_path / "grid.npz")
    np.savez(tmp_path / "partial.npz", **{k: v for k, v in arrays.items() if "encoder_norm/scale" not in k})
    with pytest.raises(VPRBenchError, match="Missing keys: .*encoder_norm/scale"):
        load_backbone(spec.name, tmp_path / "partial.npz")
    with pytest.raises(VPRBenchError, match=r"\.npz files are read for timm VisionTransformer architectures only"):
        load_backbone(tiny("dinov3_vits16", monkeypatch).name, tmp_path / "partial.npz")
    for name, other in (("pe_spatial_s16", "radio_v3_b16"), ("radio_v3_b16", "dinov3_vits16"),
                        ("dinov2_vits14_reg", "dinov2_vitb14_reg")):
        source = tiny(name, monkeypatch)
        path = write_release(create_model(source), source, tmp_path)
        with pytest.raises(VPRBenchError, match="does not fit this backbone"):
            load_backbone(tiny(other, monkeypatch, embed_dim=192 if other.startswith("dinov2_vitb") else 96).name, path)


def test_timm_names_any_vit_and_refuses_models_without_patch_tokens():
    spec = backbone_spec("timm:vit_small_patch16_dinov3.lvd1689m")
    assert (spec.patch, spec.prefix_tokens, spec.position, spec.depth) == (16, 5, "rope", 12)
    assert spec.source.hub == "timm/vit_small_patch16_dinov3.lvd1689m"
    with pytest.raises(VPRBenchError, match="timm:resnet50.a1_in1k has no patch tokens"):
        backbone_spec("timm:resnet50.a1_in1k")
    with pytest.raises(VPRBenchError, match="timm has no weights 'nope' for vit_small_patch16_dinov3; tags: lvd1689m"):
        backbone_spec("timm:vit_small_patch16_dinov3.nope")


def test_a_timm_naflexvit_keeps_its_cls_token_apart_from_its_registers():
    """NaFlexVit holds its CLS token in its embedding (embeds.cls_token): C-RADIO by its timm name has
    a CLS and 7 registers, as the shipped entry says, and takes aggregation=cls."""
    shipped = backbone_spec("radio_v3_b16")
    spec = backbone_spec("timm:naflexvit_base_patch16_radio_v3")
    assert (spec.cls_token, spec.registers, spec.cls) == (shipped.cls_token, shipped.registers, shipped.cls) \
        == (True, 7, "final-norm")
    plain = backbone_spec("timm:naflexvit_base_patch16_gap")  # registers only
    assert (plain.cls_token, plain.registers, plain.cls) == (False, 4, "none")


def test_a_vit_like_model_timm_reads_no_prefix_apart_is_refused_saying_why():
    """CaiT, XCiT and SAM's ViT have a patch embedding, blocks and patch tokens: the refusal says what
    stops them (a fixed input size; no block tokens with the prefix apart), not that they are CNNs."""
    with pytest.raises(VPRBenchError, match="timm:cait_xxs24_224 takes 224x224 inputs only"):
        backbone_spec("timm:cait_xxs24_224")
    for arch, kind in (("xcit_nano_12_p16_224", "Xcit"), ("samvit_base_patch16", "VisionTransformerSAM")):
        with pytest.raises(VPRBenchError, match=rf"timm:{arch} \({kind}\) has patch tokens, but timm gives none of "
                                                "its blocks' tokens with its class and register tokens set apart"):
            backbone_spec(f"timm:{arch}")


@pytest.mark.parametrize("arch, reason", [
    ("tnt_s_patch16_224", r"\(TNT\) embeds each patch as pixel tokens and nests inner pixel blocks in its blocks "
                          r"\(attentions attn_in, attn_out; no single attention over the patch and prefix tokens\), "
                          r"so its blocks hand no plain per-patch tokens"),
    ("mixer_s16_224", r"\(MlpMixer\) has patch tokens but no attention at all \(its blocks mix tokens with MLPs: "
                      r"no query, key or value to read\) and no class token"),
])
def test_a_patch_model_of_another_kind_is_refused_saying_what_it_is(arch, reason):
    """TNT and MLP-Mixer embed patches and have blocks: the refusal says what their blocks are, read
    from their structure (was: the general "not a ViT ... e.g. a CNN, a hybrid or a hierarchical model")."""
    with pytest.raises(VPRBenchError, match=rf"^timm:{arch} {reason}; AnyLoc aggregates per-patch ViT features: "
                                            "choose a plain ViT"):
        backbone_spec(f"timm:{arch}")


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


def test_a_facet_the_attention_cannot_give_is_refused_naming_both(monkeypatch):
    from vprbench import create_method

    entry = backbone_spec("siglip2_b16").model_copy(update={"name": "tokens_only", "facets": ("token",)})
    monkeypatch.setitem(backbones(), "tokens_only", entry)
    with pytest.raises(VPRBenchError, match=r"facet=value: backbone tokens_only gives token only"):
        create_method("anyloc", backbone="tokens_only", facet="value", weights="random", aggregation="gem")
    assert create_method("anyloc", backbone="tokens_only", facet="token", weights="random", aggregation="gem",
                         layer=3).facet == "token"


@pytest.mark.parametrize("name", ["dinov3_vits16", "pe_spatial_s16", "radio_v3_b16", "siglip2_b16", "dinov2_vits14_reg",
                                  "dinov2_vits14", "dino_vits8"])
def test_reduced_precision_flows_through_every_facet(name):
    """bf16 autocast, what precision=bf16 runs on a GPU, here on CPU (dtype flow only; speed is a GPU
    matter): q, k and v leave the hook in the autocast dtype (RoPE, computed in float32, cast back
    as timm does), the token facet is the float32 residual stream, all within bf16's rounding of fp32."""
    from vprbench.features.dense import FACETS

    spec = backbone_spec(name)
    torch.manual_seed(0)
    model = create_model(spec, **TINY)
    images = torch.randn(1, 3, 2 * spec.patch, 3 * spec.patch)
    for facet in FACETS:
        with torch.autocast("cpu", dtype=torch.bfloat16):
            reduced = DenseExtractor(model, spec, 1, facet)(images)
        full = DenseExtractor(model, spec, 1, facet)(images)
        assert reduced.dtype == (torch.float32 if facet == "token" else torch.bfloat16) and full.dtype == torch.float32
        cosine = torch.nn.functional.cosine_similarity(reduced.float(), full, dim=-1)
        assert cosine.min() > 0.999, (facet, cosine.min())


def test_a_timm_name_of_dinov3s_release_runs_as_the_release():
    """`timm:vit_small_patch16_dinov3` built its RoPE periods in timm's float32 where dinov3_vits16 (the
    same architecture and weights) keeps the release's bfloat16: its descriptors differed by ~1e-2."""
    from vprbench import create_method

    torch.manual_seed(1)
    images = [torch.rand(3, 128, 128) for _ in range(3)]
    found = {}
    for name in ("dinov3_vits16", "timm:vit_small_patch16_dinov3"):
        method = create_method("anyloc", backbone=name, weights="random", layer=11, facet="key", aggregation="gem")
        found[name] = method.describe(images), method.extractor.model.rope.periods.clone(), method.fingerprint()
    (release, periods, fp), (by_timm, timm_periods, timm_fp) = found.values()
    assert torch.equal(periods, timm_periods) and periods[1].item() == 1.3359375  # float32: 1.3335
    assert abs(release - by_timm).max() <= 1e-6
    assert fp["rope_periods"] == timm_fp["rope_periods"] == "bfloat16"  # not served the timm name's float32 stores
    # another size or variant of the release, known by the licence timm's config names it by; other weights keep timm's
    for name, periods, licence in (("timm:vit_small_patch16_dinov3_qkvb.lvd1689m", "bfloat16", "DINOv3 License"),
                                   ("timm:vit_small_plus_patch16_dinov3", "bfloat16", "DINOv3 License"),
                                   ("timm:vit_small_patch16_dinov3_qkvb.eupe_lvd1689m", "float32",
                                    "fair-noncommercial-research-license")):
        entry = backbone_spec(name)
        assert (entry.rope_periods, entry.licence, entry.gated) == (periods, licence, periods == "bfloat16")


@pytest.mark.parametrize("name", ["dinov2_vits14", "dinov3_vits16"])  # a hook on the qkv linear; on the attention
def test_two_threads_extract_through_one_model_each_its_own_facet(name):
    """A thread's pass reaches the facet's block while another thread's extraction waits there with
    its hook in place: each gets its own images' features."""
    import threading

    spec = backbone_spec(name)
    torch.manual_seed(0)
    model = create_model(spec, **TINY)
    extract = DenseExtractor(model, spec, 1, "value")
    first, second = (torch.randn(1, 3, 2 * spec.patch, 3 * spec.patch) for _ in range(2))
    alone = [extract(images) for images in (first, second)]
    waiting, passed, got = threading.Event(), threading.Event(), {}

    def hold_second(_block, _args):  # the second thread waits at block 1, its extractor's hook set
        if threading.current_thread().name == "second":
            waiting.set()
            assert passed.wait(30)

    held = model.blocks[1].register_forward_pre_hook(hold_second)
    other = threading.Thread(target=lambda: got.update(second=extract(second)), name="second")
    other.start()
    assert waiting.wait(30)
    try:
        got["first"] = extract(first)
    finally:
        passed.set()
        other.join(30)
        held.remove()
    torch.testing.assert_close(got["first"], alone[0], rtol=0, atol=0)
    torch.testing.assert_close(got["second"], alone[1], rtol=0, atol=0)
