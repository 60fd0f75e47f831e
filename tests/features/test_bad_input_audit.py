"""Bad input found by an audit of the backbones through the command line: timm names that name no
model, timm models whose tokens the dense extractor cannot read, a DINOv2 checkpoint given for the
model with registers (and the other way round), .npz files that are no archive, legacy checkpoints
holding code, an input resized below one patch, vocabularies imported under keys no features have.
Each is refused in one line naming the thing at fault and what to do, exit 1, no traceback, the
payload never runs, nothing cached (no descriptor store or store folder, result or vocabulary), and a
good run after it is not affected."""
from __future__ import annotations

import io
import os
import pickle
import warnings
import zipfile

import numpy as np
import pytest
import torch
from numpy.lib import format as npy_format

from vprbench import VPRBenchError
from vprbench.aggregation import Vocabulary
from vprbench.evaluation import read_results
from vprbench.features.backbones import create_model
from vprbench.features.catalogue import BackboneEntry, backbone_spec, backbones
from vprbench.features.dense import DenseExtractor
from vprbench.paths import cache_root

from release_formats import official_state_dict


def assert_refused(code: int, err: str, *fragments: str) -> None:
    message = err.strip()
    assert code == 1, err
    assert "Traceback" not in err and message.startswith("error: ") and "\n" not in message, err
    for fragment in fragments:
        assert fragment in message, message
    assert not read_results(), "a refused run recorded a result"
    assert not list(cache_root().rglob("*.h5")), "a refused run wrote a descriptor store"
    # was: weights of another architecture (or a resize below one patch) left empty store folders with a lock file
    assert not (cache_root() / "stores").exists(), list((cache_root() / "stores").rglob("*"))
    assert not list(cache_root().rglob("vocabulary.pt")), "a refused run cached a vocabulary"


def tiny(name: str, monkeypatch, **size) -> BackboneEntry:
    """The entry `name` at 2 blocks of width 96 (its own timm architecture), listed as `tiny-NAME`."""
    size = {"depth": 2, "embed_dim": 96, "num_heads": 2, **size}
    entry = backbone_spec(name)
    entry = entry.model_copy(update={"name": f"tiny-{name}", "depth": size["depth"], "width": size["embed_dim"],
                                     "timm_kwargs": {**entry.timm_kwargs, **size}})
    monkeypatch.setitem(backbones(), entry.name, entry)
    return entry


def evaluate(cli, shared_data, backbone: str, weights, *more):
    """One GeM evaluation of block 1 on the real Corridor, images resized to 28x42."""
    return cli("evaluate", "--method", "anyloc", "--backbone", backbone, "--weights", weights, "--layer", "1",
               "--aggregation", "gem", "--dataset", "corridor", "--data-dir", shared_data, "--quiet", *more)


# ---------------------------------------------------------------- timm:ARCH.TAG
@pytest.mark.parametrize("name", ["timm:", "timm:.", "timm:../../etc/passwd", "timm:vit_small_patch16_224.",
                                  "timm:vit_small_patch16_224/../x", "timm:vit_small;touch x",
                                  "timm: vit_small_patch16_224"])
def test_a_timm_name_that_is_no_model_name_is_refused_as_given(name, cli, shared_data):
    code, _, err = evaluate(cli, shared_data, name, "random", "--resize", "32", "32")
    assert_refused(code, err, f"Backbone {name!r} is not a timm model name", "give timm:ARCH or timm:ARCH.TAG")


def test_an_unknown_timm_architecture_says_where_names_are_listed():
    with pytest.raises(VPRBenchError, match=r"timm has no architecture 'vit_nosuch_thing'\..* Give one that "
                                            r"timm\.list_models\(\) names"):
        backbone_spec("timm:vit_nosuch_thing")


@pytest.mark.parametrize("arch", ["hiera_tiny_224", "crossvit_tiny_240", "vit_small_r26_s32_224"])
def test_a_timm_model_whose_tokens_the_extractor_cannot_read_is_refused(arch):
    # hierarchical and two-branch models, a CNN-stem hybrid (XCiT and SAM's ViT: test_anyloc_backbones.py)
    with pytest.raises(VPRBenchError, match=f"timm:{arch} has no patch tokens vprbench can read .* choose a plain ViT"):
        backbone_spec(f"timm:{arch}")


@pytest.mark.parametrize("arch, size", [("beit_base_patch16_224", "224x224"), ("test_vit_relpos", "160x160"),
                                       ("convit_tiny", "224x224"), ("cait_xxs24_224", "224x224")])
def test_a_timm_vit_of_one_input_size_is_refused(arch, size):
    with pytest.raises(VPRBenchError, match=f"timm:{arch} takes {size} inputs only .* choose a timm ViT that takes "
                                            "any size"):
        backbone_spec(f"timm:{arch}")


def test_a_refused_timm_model_exits_cleanly_through_the_command_line(cli, shared_data):
    code, _, err = evaluate(cli, shared_data, "timm:hiera_tiny_224", "random", "--resize", "32", "32")
    assert_refused(code, err, "timm:hiera_tiny_224 has no patch tokens vprbench can read")


def test_a_timm_vit_without_prefix_tokens_gives_its_patch_tokens():
    # Perception Encoder gigantic (an Eva) has neither CLS nor register tokens
    spec = backbone_spec("timm:vit_pe_core_gigantic_patch14_448")
    assert spec.prefix_tokens == 0
    torch.manual_seed(0)
    model = create_model(spec, depth=2, embed_dim=96, num_heads=2)
    images = torch.randn(1, 3, 2 * spec.patch, 3 * spec.patch)
    tokens = DenseExtractor(model, spec, 1, "token")(images)
    with torch.no_grad():
        expected = model.forward_intermediates(images, indices=[1], norm=False, output_fmt="NLC",
                                               intermediates_only=True)[0]
    assert tokens.shape == (1, 6, 96) and torch.allclose(tokens, expected, atol=1e-5)


# ---------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("official", [False, True], ids=["timm-format", "release-format"])
def test_dinov2_weights_and_the_registers_model_are_refused_both_ways(official, cli, shared_data, tmp_path,
                                                                      monkeypatch):
    plain, registers = tiny("dinov2_vits14", monkeypatch), tiny("dinov2_vits14_reg", monkeypatch)
    files = {}
    for spec in (plain, registers):
        torch.manual_seed(0)
        model = create_model(spec)
        files[spec.name] = tmp_path / f"{spec.name}.pth"
        torch.save(official_state_dict(model, spec) if official else model.state_dict(), files[spec.name])
    # the release with registers holds one position more (the CLS slot), which timm's converter drops
    plain_file = ["Missing keys: reg_token", "pos_embed: file (1, 1370, 96) vs model (1, 1369, 96)"]
    registers_file = ["register_tokens"] if official else ["Unexpected keys: reg_token",
                                                           "pos_embed: file (1, 1369, 96) vs model (1, 1370, 96)"]
    for backbone, other, said in ((registers, plain, plain_file), (plain, registers, registers_file)):
        code, _, err = evaluate(cli, shared_data, backbone.name, files[other.name], "--resize", "28", "42")
        assert_refused(code, err, f"{files[other.name]} for backbone {backbone.name}: The weights file does not fit",
                       *said, "Pass a checkpoint of this backbone, or choose the backbone the file was saved from.")
    code, _, err = evaluate(cli, shared_data, registers.name, files[registers.name], "--resize", "28", "42")
    assert code == 0, err  # the good run after the refused ones
    assert len(read_results()) == 1


@pytest.mark.parametrize("content", [b"", b"garbage, not an archive", "truncated", "claims terabytes"])
def test_npz_weights_that_are_no_archive_are_refused_without_advice_to_unpickle(content, cli, shared_data, tmp_path,
                                                                              monkeypatch):
    spec = tiny("siglip2_b16", monkeypatch)
    path = tmp_path / "siglip2_b16_224.npz"
    said = "it is not a complete .npz archive"
    if content == "truncated":
        np.savez(path, **{"params/img/embedding/kernel": np.zeros((16, 16, 3, 96), np.float32)})
        content = path.read_bytes()[:-40]
    if content == "claims terabytes":  # a kernel whose header claims 8 TB, in a file of a few hundred bytes
        header = io.BytesIO()
        npy_format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (10**12,)})
        with zipfile.ZipFile(path, "w") as archive:
            archive.writestr("params/img/embedding/kernel.npy", header.getvalue() + bytes(16))
        content, said = path.read_bytes(), "its member params/img/embedding/kernel.npy: it is truncated"
    path.write_bytes(content)
    code, _, err = evaluate(cli, shared_data, spec.name, path, "--resize", "32", "32")
    assert_refused(code, err, f"Cannot read weights file {path}: {said}",
                   "pass the release file as published (download it again), or another")
    assert "allow_pickle" not in err


class Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_legacy_checkpoint_holding_code_names_it_and_never_runs_it(cli, shared_data, tmp_path):
    marker = tmp_path / "payload-ran"
    legacy, raw = tmp_path / "legacy.pth", tmp_path / "raw.pth"
    torch.save({"weights": Payload(marker)}, legacy, _use_new_zipfile_serialization=False)
    raw.write_bytes(pickle.dumps({"weights": Payload(marker)}, protocol=4))
    code, _, err = evaluate(cli, shared_data, "dinov2_vits14", legacy)
    assert_refused(code, err, f"Weights file {legacy} also holds Python objects (posix.system), which are not loaded")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, _, err = evaluate(cli, shared_data, "dinov2_vits14", raw)
    assert_refused(code, err, f"Cannot read weights file {raw}: it is damaged or not a PyTorch file")
    assert not [w for w in caught if "pickle protocol" in str(w.message)], "a second line beside the refusal"
    assert not marker.exists(), "the payload ran"


# ---------------------------------------------------------------- input size
def test_a_resize_below_one_patch_says_what_to_do(cli, shared_data, monkeypatch):
    spec = tiny("dinov3_vits16", monkeypatch)
    code, _, err = evaluate(cli, shared_data, spec.name, "random", "--resize", "8", "8")
    assert_refused(code, err, "Image of 8x8 pixels is smaller than one 16x16 patch: resize to at least 16x16")


def test_images_below_one_patch_are_named_before_any_store_folder_exists(cli, monkeypatch, tmp_path):
    from PIL import Image

    spec = tiny("dinov3_vits16", monkeypatch)
    rows = ["image,x,y"]
    for split in ("database", "queries"):
        (tmp_path / "small" / split).mkdir(parents=True)
        for i in range(2):
            Image.new("RGB", (12, 10), (i * 90, 40, 200)).save(tmp_path / "small" / split / f"{i}.png")
            rows.append(f"{split}/{i}.png,{i},0")
    (tmp_path / "small" / "positions.csv").write_text("\n".join(rows) + "\n")
    code, _, err = cli("evaluate", "--method", "anyloc", "--backbone", spec.name, "--weights", "random", "--layer", "1",
                       "--aggregation", "gem", "--dataset", tmp_path / "small", "--k", "1", "--quiet")
    assert_refused(code, err, f"Image {tmp_path / 'small' / 'database' / '0.png'} of 10x12 pixels is smaller than "
                              "one 16x16 patch: resize to at least 16x16")


# ---------------------------------------------------------------- vocabulary import
@pytest.mark.parametrize("backbone, layer, facet, source, said", [
    ("dinov2_vits14", 12, "value", "indoor", "option --layer takes a whole number from 0 to 11 (0-based block of "
                                             "dinov2_vits14); got 12"),
    ("dinov2_vits14", 3, "bogus", "indoor", "option --facet takes one of token, query, key, value; got 'bogus'"),
    ("nosuch", 3, "value", "indoor", "Unknown backbone 'nosuch'"),
    ("dinov2_vitb14", 3, "value", "indoor", "has 384-dimensional centres but the features are 768-dimensional"),
    ("dinov2_vits14", 3, "value", "../../escape", "--source '../../escape' is not a vocabulary name"),
    ("dinov2_vits14", 3, "value", "map-", "--source 'map-' is not a vocabulary name: give a domain"),
    ("dinov2_vits14", 3, "value", "map-a/b", "map-DATASET with a dataset's name (1 to 100 letters"),
    ("dinov2_vits14", 3, "value", "map-.hidden", "--source 'map-.hidden' is not a vocabulary name"),
    ("dinov2_vits14", 3, "value", "x" * 300, "or another name of 1 to 100 letters, digits, '_' or '-'"),
])
def test_a_vocabulary_imported_under_a_key_no_features_have_is_refused(backbone, layer, facet, source, said, cli,
                                                                       tmp_path):
    centres = tmp_path / "centres.pt"
    Vocabulary(torch.randn(4, 384)).save(centres)
    code, _, err = cli("vocabulary", "import", centres, "--source", source, "--backbone", backbone, "--layer", layer,
                       "--facet", facet)
    assert_refused(code, err, said)
    assert not [p for p in tmp_path.rglob("*.pt") if p != centres], "written outside the key"
    code, out, err = cli("vocabulary", "import", centres, "--source", "indoor", "--backbone", "dinov2_vits14@random",
                         "--layer", "3", "--facet", "value")
    assert code == 0 and "Imported 4 x 384 centres as 'indoor'" in out, err
