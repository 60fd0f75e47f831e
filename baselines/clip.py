"""CLIP CLS baseline of the AnyLoc paper: OpenCLIP ViT-bigG-14 (LAION-2B) image embedding, L2-normalised.

The descriptor is OpenCLIP's `encode_image` output: the final-norm CLS token times the
image projection (1280-D for ViT-bigG-14). Only the image tower is materialised; the text
tower is built on the meta device so that the checkpoint's full key list can still be
checked exactly.

Preprocessing `anyloc` (default) repeats the AnyLoc evaluation: ToTensor, ImageNet
normalisation, the optional dataset resize on that tensor (bilinear, no antialiasing),
then the tensor is turned back into an 8-bit image by per-image min-max scaling before
OpenCLIP's own transform (shorter side 224 bicubic, centre crop 224, CLIP mean/std).
`openclip` applies OpenCLIP's transform to the image file directly.
"""
from __future__ import annotations

import logging
import posixpath
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torchvision.transforms.functional as TF
from PIL import Image
from torch import nn

from vprbench import VPRBenchError
from vprbench.errors import closest_names
from vprbench.images import load_image

from .common import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    TorchMethod,
    WeightSource,
    as_resize,
    choose,
    file_sha256,  # noqa: F401  (tests name a file's identity through the baseline)
    load_exact,
    native_when_unset,
    read_weights_file,
    resolve_weights,
    state_dict_of,
    weights_fields,
)

METHOD = "clip-cls"
PREPROCESSING = ("anyloc", "openclip")
DEFAULT_FILE = "open_clip_pytorch_model.bin"  # OpenCLIP's file in a hub repository


@dataclass(frozen=True)
class ClipPreprocess:
    """Image file -> CLIP input tensor (see the module docstring)."""

    image_size: tuple[int, int]
    mean: tuple[float, ...]
    std: tuple[float, ...]
    interpolation: str = "bicubic"
    resize_mode: str = "shortest"
    mode: str = "anyloc"
    resize: tuple[int, int] | None = None

    def transform(self):
        import open_clip

        return open_clip.image_transform(
            self.image_size, is_train=False, mean=self.mean, std=self.std,
            resize_mode=self.resize_mode, interpolation=self.interpolation,
        )

    def __call__(self, path: Path) -> torch.Tensor:
        image = load_image(path, "RGB")
        if self.mode == "anyloc":
            image = anyloc_round_trip(image, self.resize)
        elif self.resize is not None:
            image = image.resize((self.resize[1], self.resize[0]), Image.BILINEAR)
        return self.transform()(image)

    def fingerprint(self) -> dict:
        return {
            "mode": self.mode, "resize": list(self.resize) if self.resize else None,
            "image_size": list(self.image_size), "mean": list(self.mean), "std": list(self.std),
            "interpolation": self.interpolation, "resize_mode": self.resize_mode,
        }


def anyloc_round_trip(image: Image.Image, resize: tuple[int, int] | None) -> Image.Image:
    """AnyLoc's CLIP input: the ImageNet-normalised (and resized) tensor, min-max scaled back to 8 bits."""
    x = TF.normalize(TF.to_tensor(image), IMAGENET_MEAN, IMAGENET_STD)
    if resize is not None:
        x = TF.resize(x, list(resize), antialias=False)  # the 2023 torchvision tensor default
    x = x.permute(1, 2, 0).numpy().astype(np.float64)
    x = (x - x.min()) / (x.max() - x.min())  # over all channels at once, as the authors' code
    return Image.fromarray((x * 255).astype(np.uint8))


class ClipImageEncoder(nn.Module):
    """OpenCLIP's image tower; forward = `CLIP.encode_image` (unnormalised)."""

    def __init__(self, visual: nn.Module):
        super().__init__()
        self.visual = visual

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.visual(images)


def _check_backbone(backbone: str, pretrained: str | None, weights) -> None:
    import open_clip

    models = open_clip.list_models()
    if backbone not in models:
        raise VPRBenchError(
            f"{METHOD}: unknown OpenCLIP architecture {backbone!r}.{closest_names(backbone, models)} "
            f"Valid: {', '.join(models)}."
        )
    if weights is None:
        tags = open_clip.list_pretrained_tags_by_model(backbone)
        if pretrained not in tags:
            raise VPRBenchError(
                f"{METHOD}: OpenCLIP publishes no weights {pretrained!r} for {backbone}; "
                f"valid: {', '.join(tags) or 'none (pass --weights PATH)'}."
            )


def weight_source(backbone: str, pretrained: str | None) -> WeightSource:
    """Where OpenCLIP publishes `backbone`'s `pretrained` weights: a hub file (its 'org/repo/'
    entries mean the default file name) or a URL."""
    import open_clip

    cfg = open_clip.get_pretrained_cfg(backbone, pretrained) if pretrained else {}
    if cfg.get("hf_hub"):
        repo, name = posixpath.split(cfg["hf_hub"])  # as OpenCLIP splits it
        return WeightSource(name or DEFAULT_FILE, hub=repo)
    if cfg.get("url"):
        return WeightSource(cfg["url"].rsplit("/", 1)[-1], url=cfg["url"])
    return WeightSource(DEFAULT_FILE, page="the OpenCLIP release")


def resolve_clip_weights(backbone: str, pretrained: str, weights, cache_dir=None) -> tuple[Path, dict]:
    """(checkpoint file, identity): the user's file, or OpenCLIP's published one (downloaded once)."""
    source = weight_source(backbone, pretrained)
    resolved = resolve_weights(source, weights, METHOD, cache_dir=cache_dir)
    return resolved.path, weights_fields(resolved, source)


def _read(path: Path) -> dict:
    # mmap: the 10 GB ViT-bigG-14 file is not copied into memory a second time
    return state_dict_of(read_weights_file(path, f"{METHOD} checkpoint"))


def load_image_tower(backbone: str, path: Path) -> nn.Module:
    """The image tower of `backbone` holding the weights in `path` (whose keys must match exactly)."""
    import open_clip

    # an empty model, filled from `path` below: OpenCLIP's "no pretrained weights" log line would mislead
    logger = logging.getLogger()
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with torch.device("meta"):
            full = open_clip.create_model(backbone, device="meta")
    finally:
        logger.setLevel(level)
    state = _read(path)
    with warnings.catch_warnings():  # copying into meta tensors is a deliberate no-op: only the key check matters
        warnings.simplefilter("ignore", UserWarning)
        load_exact(full, state, METHOD)  # names missing, unexpected and mis-shaped keys
    visual = full.visual
    image_state = {k[len("visual."):]: v for k, v in state.items() if k.startswith("visual.")}
    visual.load_state_dict(image_state, strict=True, assign=True)  # takes the tensors, no copy
    return visual.float()


def clip_cls(backbone="ViT-bigG-14", pretrained="laion2b_s39b_b160k", weights=None, resize=None, preprocess="anyloc",
             batch_size=None, precision="fp32", device="cpu", cache_dir=None):
    import open_clip

    mode = choose("preprocess", preprocess, PREPROCESSING, METHOD)
    resize = as_resize(resize)
    _check_backbone(backbone, pretrained, weights)
    path, identity = resolve_clip_weights(backbone, pretrained, weights, cache_dir)
    visual = load_image_tower(backbone, path)
    pp = dict(getattr(visual, "preprocess_cfg", {}))
    if pretrained in open_clip.list_pretrained_tags_by_model(backbone):  # the published weights' own settings
        published = open_clip.get_pretrained_cfg(backbone, pretrained)
        pp.update({k: published[k] for k in ("mean", "std", "interpolation", "resize_mode") if published.get(k)})
    size = visual.image_size if isinstance(visual.image_size, tuple) else (visual.image_size, visual.image_size)
    preprocessing = ClipPreprocess(
        image_size=tuple(size),
        mean=tuple(pp.get("mean", open_clip.OPENAI_DATASET_MEAN)),
        std=tuple(pp.get("std", open_clip.OPENAI_DATASET_STD)),
        interpolation=pp.get("interpolation", "bicubic"),
        resize_mode=pp.get("resize_mode", "shortest"),
        mode=mode,
        resize=resize,
    )
    dim = visual.output_dim
    tag = pretrained if weights is None else None  # a local file is identified by its hash
    fingerprint = {"method": METHOD, **identity, "backbone": backbone, "pretrained": tag, "dim": dim}
    return TorchMethod(ClipImageEncoder(visual), preprocessing, fingerprint, batch_size=batch_size, device=device,
                       precision=precision, dim=dim)

#: unset resize is the image as stored: resize=native written out is the same run
clip_cls.implied_options = native_when_unset
