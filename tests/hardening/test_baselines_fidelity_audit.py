"""The VPR-trained baselines against their authors' released code: what decides their numbers.

Architectures, parameter layouts, aggregations and weight sources were compared with the
authors' code (random weights loaded into both, descriptors equal to ~1e-8); these tests hold
the differences that were found and fixed.
"""
import inspect
from pathlib import Path

import numpy as np
import pytest
import torch
import torchvision.transforms as T
from PIL import Image

from vprbench_baselines import boq, netvlad
from vprbench_baselines.vit import ViTConfig

IMAGENET = dict(mean=[0.485, 0.456, 0.406], std=[0.229, 0.224, 0.225])
DOCS = Path(__file__).resolve().parents[2] / "docs" / "baselines.md"


def _checkerboard(path: Path, width: int = 20, height: int = 15) -> Path:
    """Black/white squares: upsampling them with bicubic overshoots [0, 1] at every edge."""
    rng = np.random.default_rng(0)
    cells = (np.indices((height, width)).sum(axis=0) % 2).astype(np.uint8) * 255
    image = np.stack([cells, 255 - cells, rng.integers(0, 256, (height, width), dtype=np.uint8)], axis=-1)
    Image.fromarray(image).save(path)
    return path


def _tiny_boq(tmp_path: Path):
    config = boq.BoQConfig("dinov2", 64, (56, 56), "tiny.pth", vit=ViTConfig(embed_dim=32, depth=2, heads=2),
                           queries=4, row_dim=2)
    model = boq.BoQ(config)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in model.parameters():
            p.copy_(torch.randn_like(p) * 0.05)
    torch.save(model.state_dict(), tmp_path / "tiny.pth")
    return boq.build(config, weights=str(tmp_path / "tiny.pth")), model.eval()


def test_boq_input_is_the_authors_tensor_transform(tmp_path):
    """The authors' transform for the released BoQ models: ToTensor, then a bicubic antialiased
    resize of the float tensor, then Normalize. Resizing the 8-bit image first (as before)
    clipped bicubic's overshoot and rounded to 1/255 (inputs off by up to 0.06 on a Corridor image)."""
    method, model = _tiny_boq(tmp_path)
    path = _checkerboard(tmp_path / "board.png")
    authors = T.Compose([
        T.ToTensor(),
        T.Resize((56, 56), interpolation=T.InterpolationMode.BICUBIC, antialias=True),
        T.Normalize(**IMAGENET),
    ])(Image.open(path).convert("RGB"))
    ours = method.preprocess(path)
    assert ours.shape == authors.shape == (3, 56, 56)
    np.testing.assert_allclose(ours.numpy(), authors.numpy(), atol=1e-5)
    with torch.no_grad():
        expected = model(authors[None])[0].numpy()
    np.testing.assert_allclose(method.describe([path])[0], expected / np.linalg.norm(expected), atol=1e-5)
    assert method.fingerprint()["preprocess"]["normalise_first"] is True


def _docs_row(method: str) -> list[str]:
    for line in DOCS.read_text().splitlines():
        if line.startswith(f"| `{method}` |"):
            return [cell.strip() for cell in line.strip("|").split(" | ")]
    raise AssertionError(f"no row for {method} in {DOCS}")


def test_netvlad_vgg16_docs_state_its_input_and_file():
    """The default (4096-d WPCA) model reads 480x640 images, as the release's extraction configs,
    from the hub file pitts_WPCA4096.pth.tar; the page said 'full resolution' and another file name."""
    assert inspect.signature(netvlad.netvlad_vgg16).parameters["dim"].default == 4096
    _, _, dim, given, weights = _docs_row("netvlad-vgg16")
    assert dim == "4096"
    assert given.startswith("480x640"), given
    assert "full resolution for 32768-d" in given, given
    hub_file = netvlad.PATCH_NETVLAD_URL.format(prefix="pitts", dim=4096).rsplit("/", 1)[1]
    assert f"`{hub_file}`" in weights, weights


@pytest.mark.parametrize("dim", netvlad.WPCA_DIMS)
def test_netvlad_vgg16_wpca_default_resize(dim, monkeypatch):
    """The docs row above describes what the factory does (no weights are read: the loader is stubbed)."""
    monkeypatch.setattr(netvlad, "load_checkpoint", lambda *a, **k: ({}, {"weights_sha256": "0"}))
    monkeypatch.setattr(netvlad, "build_loaded", lambda build, state, name: torch.nn.Identity())
    method = netvlad.netvlad_vgg16(dim=dim)
    assert method.preprocess.resize == (480, 640) and method.preprocess.interpolation == "bilinear"
    assert method.preprocess.normalise_first is False  # PIL resize of the image, as torchvision Resize on it
