"""Backbone manifests as hostile data: a value of the wrong type, a stride that does not divide the
patch, non-finite or zero normalisation, facets listed twice or without the token, timm keywords that
would load weights behind the resolver's back, a malformed sha256, URL, page or name are each refused
naming the entry and the field; a timm:ARCH name of a shipped entry's weights keeps its licence and
gating; a q/k/v facet an entry lists for a block without q/k/v projections is refused in one line."""
from __future__ import annotations

import re

import pytest

from vprbench import VPRBenchError
from vprbench.features.catalogue import _entries, backbone_spec
from vprbench.weights import local_weights

GOOD = {
    "family": '"X"', "patch": "14", "cls_token": "true", "registers": "0", "position": '"learned"',
    "position_interpolation": '"dino"', "mean": "[0.5, 0.5, 0.5]", "std": "[0.5, 0.5, 0.5]", "resize": '"crop"',
    "interpolation": '"bilinear"', "facets": '["token", "query", "key", "value"]', "preprocess": '"p"',
    "cls": '"final-norm"', "normalise_patches": '"always"', "licence": '"MIT"', "gated": "false",
    "page": '"https://example.org/x"', "name": '"b"', "timm": '"vit_small_patch14_dinov2"', "depth": "12",
    "width": "384", "url": '"https://example.org/x/b.pth"',
}


def manifest(**change: str) -> str:
    fields = {**GOOD, **change}
    return "[[backbone]]\n" + "".join(f"{key} = {value}\n" for key, value in fields.items())


def test_a_good_entry_is_read():
    (entry,) = _entries(manifest(), "good.toml")
    assert (entry.patch, entry.depth, entry.gated, entry.sha256) == (14, 12, False, None)


@pytest.mark.parametrize("change, said", [
    ({"sha256": '"zz"'}, "sha256: 'zz' is not a sha256 (64 hexadecimal digits)"),
    ({"stride": "0"}, "stride: Input should be greater than 0"),
    ({"stride": "28"}, "stride 28 does not divide the patch 14; give a divisor of it"),
    ({"std": "[0, 0.5, 0.5]"}, "std.0: Input should be greater than 0"),
    ({"mean": "[nan, 0.5, 0.5]"}, "mean.0: Input should be a finite number"),
    ({"facets": '["token", "token"]'}, "facets ['token', 'token']: list each facet once, 'token' among them"),
    ({"facets": "[]"}, "facets []: list each facet once"),
    ({"facets": '["value"]'}, "facets ['value']: list each facet once, 'token' among them"),
    ({"timm_kwargs": "{ pretrained = true }"}, "timm_kwargs pretrained: vprbench loads the weights itself"),
    ({"timm_kwargs": '{ checkpoint_path = "/tmp/x.pth" }'}, "timm_kwargs checkpoint_path: vprbench loads"),
    ({"gated": '"no"'}, "gated: Input should be a valid boolean"),
    ({"patch": "true"}, "patch: Input should be a valid integer"),
    ({"depth": "12.0"}, "depth: Input should be a valid integer"),
    ({"url": '"ftp://example.org/b.pth"'}, "url: 'ftp://example.org/b.pth' is not an https:// address of a file"),
    ({"url": '"https://example.org/"'}, "url: 'https://example.org/' is not an https:// address of a file"),
    ({"page": '"javascript:alert(1)"'}, "page: 'javascript:alert(1)' is not an https:// address"),
    ({"timm": '"../vit"'}, "timm: '../vit' is not a timm architecture (letters, digits, _)"),
    ({"licence": '""'}, "licence: String should have at least 1 character"),
    ({"resize": '"fixed"', "input_size": "[0, 224]"}, "input_size.0: Input should be greater than 0"),
])
def test_a_malformed_entry_is_refused_naming_entry_and_field(change, said):
    with pytest.raises(VPRBenchError) as error:
        _entries(manifest(**change), "bad.toml")
    message = str(error.value)
    assert message.startswith("Backbone manifest bad.toml, entry 'b': ") and said in message, message
    assert "Value error" not in message and "should match pattern" not in message and "\n" not in message


def test_a_manifest_that_is_no_toml_is_named():
    with pytest.raises(VPRBenchError, match=r"^Backbone manifest bad.toml is not valid TOML \(.*\); fix it.$"):
        _entries(manifest(depth="12\ndepth = 13"), "bad.toml")


def test_a_timm_name_of_gated_weights_is_gated_and_names_its_weights_tag(tmp_path):
    shipped, by_timm = backbone_spec("dinov3_vits16"), backbone_spec("timm:vit_small_patch16_dinov3")
    assert (by_timm.licence, by_timm.gated, by_timm.page) == (shipped.licence, True, shipped.page)
    assert by_timm.card() == {"name": "timm:vit_small_patch16_dinov3", "family": "timm",
                              "timm": "vit_small_patch16_dinov3.lvd1689m", "licence": "DINOv3 License",
                              "gated": True, "access": "https://github.com/facebookresearch/dinov3"}
    with pytest.raises(VPRBenchError) as error:
        local_weights(by_timm.source, tmp_path / "missing.safetensors", "backbone x")
    assert re.search(r"The weights are gated \(DINOv3 License\): request access at "
                     r"https://github.com/facebookresearch/dinov3 first\.$", str(error.value)), error.value
    # weights no manifest lists keep timm's own licence, not gated
    other = backbone_spec("timm:vit_small_patch16_224.augreg_in21k")
    assert (other.licence, other.gated, other.tag) == ("apache-2.0", False, "augreg_in21k")


@pytest.mark.parametrize("arch", ["vit_small_patch16_18x2_224", "vit_pwee_patch16_reg1_gap_256"])
def test_a_facet_a_parallel_block_cannot_give_is_refused_though_the_entry_lists_it(arch):
    import torch

    from vprbench.features.backbones import create_model
    from vprbench.features.dense import DenseExtractor

    spec = backbone_spec(f"timm:{arch}")
    assert spec.facets == ("token",)  # timm:ARCH reads the attention kind itself
    spec = spec.model_copy(update={"facets": ("token", "query", "key", "value")})  # a manifest claiming more
    model = create_model(spec, depth=2)
    with pytest.raises(VPRBenchError, match=rf"^Facet 'value': block 1 of timm:{arch} \(Parallel\w+Block\) has no "
                                            r"separate query/key/value projection; use facet token.$"):
        DenseExtractor(model, spec, 1, "value")
    tokens = DenseExtractor(model, spec, 1, "token")(torch.randn(1, 3, 32, 48))
    assert tokens.shape == (1, 6, spec.width)
