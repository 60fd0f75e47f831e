"""CLIP CLS baseline: OpenCLIP image embedding, AnyLoc's input path, weights and bad input.

Forwards use a tiny OpenCLIP ViT config of the same family (registered with OpenCLIP as a
third party would) and a weights file in OpenCLIP's format; ViT-bigG-14 is only built on
the meta device.
"""
import json
from pathlib import Path

import numpy as np
import open_clip
import pytest
import torch
import torchvision.transforms.functional as TF
from PIL import Image

from vprbench import VPRBenchError, create_method
from vprbench_baselines import clip

CHECKPOINTS = Path(__file__).resolve().parents[1] / "data" / "checkpoints"
TINY = "vprbench-test-tiny-vit"
TINY_CONFIG = {
    "embed_dim": 24,
    "vision_cfg": {"image_size": 28, "layers": 2, "width": 32, "head_width": 16, "patch_size": 14},
    "text_cfg": {"context_length": 8, "vocab_size": 64, "width": 16, "heads": 1, "layers": 1},
}


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
    """(architecture name, open_clip_pytorch_model.bin) of a random tiny OpenCLIP ViT."""
    folder = tmp_path_factory.mktemp("openclip")
    (folder / f"{TINY}.json").write_text(json.dumps(TINY_CONFIG))
    open_clip.add_model_config(folder / f"{TINY}.json")
    torch.manual_seed(0)
    model = open_clip.create_model(TINY)
    path = folder / "open_clip_pytorch_model.bin"
    torch.save(model.state_dict(), path)
    return path


def image(tmp_path, name="a.png", size=(61, 45), seed=0):
    rng = np.random.default_rng(seed)
    path = tmp_path / name
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)
    return path


@pytest.fixture
def no_network(monkeypatch):
    def refuse(*args, **kwargs):
        raise FileNotFoundError("no network in tests")

    import huggingface_hub.constants

    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(open_clip.pretrained, "hf_hub_download", refuse)
    monkeypatch.setattr(open_clip.pretrained.urllib.request, "urlopen", refuse)


def reference(weights, images, prepare):
    """OpenCLIP's own loading and encode_image, L2-normalised."""
    model, _, preprocess = open_clip.create_model_and_transforms(TINY, pretrained=str(weights))
    batch = torch.stack([preprocess(prepare(Image.open(p).convert("RGB"))) for p in images])
    with torch.no_grad():
        return torch.nn.functional.normalize(model.eval().encode_image(batch), dim=-1).numpy()


def test_bigg_image_and_text_layout_matches_openclip_release():
    expected = json.loads((CHECKPOINTS / "clip-vit-bigg-14.json").read_text())
    with torch.device("meta"):
        model = open_clip.create_model("ViT-bigG-14", device="meta")
    assert {k: list(v.shape) for k, v in model.state_dict().items()} == expected
    assert model.visual.output_dim == 1280 and expected["visual.proj"] == [1664, 1280]


def test_openclip_preprocessing_matches_encode_image(tmp_path, tiny_weights):
    paths = [image(tmp_path, "a.png"), image(tmp_path, "b.png", (30, 40), seed=1)]
    method = create_method("clip-cls", backbone=TINY, weights=str(tiny_weights), preprocess="openclip")
    out = method.describe(paths)
    assert out.shape == (2, 24) and out.dtype == np.float32
    np.testing.assert_allclose(out, reference(tiny_weights, paths, lambda im: im), atol=1e-5)
    np.testing.assert_allclose(out[1:], method.describe(paths[1:]), atol=1e-5)


def test_anyloc_preprocessing_round_trip(tmp_path, tiny_weights):
    paths = [image(tmp_path, "a.png")]
    method = create_method("clip-cls", backbone=TINY, weights=str(tiny_weights), resize=(32, 48))
    assert method.preprocess.mode == "anyloc"

    def anyloc_input(im):  # ImageNet-normalise, resize the tensor, min-max back to 8 bits
        x = TF.normalize(TF.to_tensor(im), (0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
        x = TF.resize(x, [32, 48], antialias=False).permute(1, 2, 0).numpy().astype(np.float64)
        return Image.fromarray(((x - x.min()) / (x.max() - x.min()) * 255).astype(np.uint8))

    np.testing.assert_allclose(method.describe(paths), reference(tiny_weights, paths, anyloc_input), atol=1e-5)
    round_trip = np.asarray(clip.anyloc_round_trip(Image.open(paths[0]).convert("RGB"), (32, 48)))
    assert round_trip.shape == (32, 48, 3) and round_trip.min() == 0 and round_trip.max() == 255
    fp = method.fingerprint()
    assert fp["dim"] == 24 and fp["backbone"] == TINY and len(fp["weights_sha256"]) == 64
    assert fp["preprocess"]["mode"] == "anyloc" and fp["preprocess"]["resize"] == [32, 48]
    assert fp["preprocess"]["image_size"] == [28, 28] and fp["preprocess"]["interpolation"] == "bicubic"


def test_published_preprocessing_of_the_paper_model():
    cfg = open_clip.get_pretrained_cfg("ViT-bigG-14", "laion2b_s39b_b160k")
    assert cfg["hf_hub"].startswith("laion/CLIP-ViT-bigG-14-laion2B-39B-b160k")
    assert tuple(cfg["mean"]) == open_clip.OPENAI_DATASET_MEAN and cfg["resize_mode"] == "shortest"


def test_legacy_format_file_and_unreadable_file(tmp_path, tiny_weights):
    state = torch.load(tiny_weights, weights_only=True)
    torch.save(state, tmp_path / "legacy.pt", _use_new_zipfile_serialization=False)
    method = create_method("clip-cls", backbone=TINY, weights=str(tmp_path / "legacy.pt"))
    assert method.fingerprint()["weights_sha256"] == clip.file_sha256(tmp_path / "legacy.pt")
    (tmp_path / "broken.bin").write_bytes(b"half a file")
    with pytest.raises(VPRBenchError, match="Cannot read clip-cls checkpoint .*broken.bin: it is damaged or not a PyTorch file"):
        create_method("clip-cls", backbone=TINY, weights=str(tmp_path / "broken.bin"))


def test_checkpoint_mismatch_names_the_keys(tmp_path, tiny_weights):
    state = torch.load(tiny_weights, weights_only=True)
    del state["visual.proj"]
    state["visual.extra"] = torch.zeros(1)
    state["visual.class_embedding"] = torch.zeros(7)
    torch.save(state, tmp_path / "bad.bin")
    with pytest.raises(VPRBenchError) as info:
        create_method("clip-cls", backbone=TINY, weights=str(tmp_path / "bad.bin"))
    message = str(info.value)
    assert "missing: visual.proj" in message and "unexpected: visual.extra" in message
    assert "visual.class_embedding (7,) (expected (32,))" in message


def test_offline_without_weights_says_how_to_supply_them(no_network):
    with pytest.raises(VPRBenchError) as info:
        create_method("clip-cls")
    message = str(info.value)
    assert "--weights PATH" in message and "open_clip_pytorch_model.bin" in message
    assert "https://huggingface.co/laion/CLIP-ViT-bigG-14-laion2B-39B-b160k" in message


@pytest.mark.parametrize(
    "options, pattern",
    [
        ({"backbone": "ViT-bigG-15"}, r"unknown OpenCLIP architecture 'ViT-bigG-15'. Did you mean: ViT-bigG-14"),
        ({"pretrained": "laion400m"}, r"no weights 'laion400m' for ViT-bigG-14; valid: laion2b_s39b_b160k"),
        ({"preprocess": "five-crop"}, r"unknown preprocess 'five-crop'; valid: anyloc, openclip"),
    ],
)
def test_invalid_options_list_valid_ones(options, pattern, no_network):
    with pytest.raises(VPRBenchError, match=pattern):
        create_method("clip-cls", **options)


def test_real_corridor_images(shared_data, tiny_weights):
    """Real 160x120 fisheye frames through the paper's CLIP path (ImageNet round trip, 224 crop)."""
    paths = sorted((shared_data / "corridor" / "ref").glob("*.jpg"))[:3]
    assert len(paths) == 3
    method = create_method("clip-cls", backbone=TINY, weights=str(tiny_weights))
    out = method.describe(paths)
    assert out.shape == (3, 24)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(out, reference(tiny_weights, paths, lambda im: clip.anyloc_round_trip(im, None)), atol=1e-5)
