"""MegaLoc (Berton & Masone, CVPRW 2025): DINOv2 ViT-B/14 + SALAD-style aggregation + linear to 8448.

Matches the authors' released `model.safetensors` (parameter names `backbone.*`,
`aggregator.agg.*`, `aggregator.linear.*`) and their model's own input handling: full
resolution, ImageNet normalisation, sides not divisible by 14 resized (bilinear,
antialiased) to the nearest multiple of 14.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
import torchvision.transforms.functional as TF
from torch import nn


from .common import (
    Preprocess,
    TorchMethod,
    WeightSource,
    as_resize,
    check_dim,
    choose,
    load_checkpoint,
    load_exact,
    native_when_unset,
    state_dict_of,
)
from .salad import SaladAggregator
from .vit import DINOV2_VITB14, ViTConfig, dinov2_vit, patch_map, vit_tokens

METHOD = "megaloc"
WEIGHTS = WeightSource(
    "megaloc-model.safetensors",  # saved under this name in the cache; the hub file is model.safetensors
    url="https://huggingface.co/gberton/MegaLoc/resolve/main/model.safetensors",
    page="https://huggingface.co/gberton/MegaLoc",
)
BACKBONES = {"dinov2_vitb14": 768}


@dataclass(frozen=True)
class MegaLocConfig:
    vit: ViTConfig = field(default_factory=lambda: DINOV2_VITB14)
    clusters: int = 64
    cluster_dim: int = 256
    token_dim: int = 256
    hidden: int = 512
    dim: int = 8448


class MegaLocAggregator(nn.Module):
    def __init__(self, config: MegaLocConfig):
        super().__init__()
        self.agg = SaladAggregator(
            config.vit.embed_dim, config.clusters, config.cluster_dim, config.token_dim, config.hidden
        )
        self.linear = nn.Linear(config.clusters * config.cluster_dim + config.token_dim, config.dim)

    def forward(self, features: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
        return self.linear(self.agg(features, token))


class MegaLoc(nn.Module):
    def __init__(self, config: MegaLocConfig = MegaLocConfig()):
        super().__init__()
        self.patch = config.vit.patch
        self.backbone = dinov2_vit(config.vit)
        self.aggregator = MegaLocAggregator(config)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[-2:]
        if height % self.patch or width % self.patch:  # as the released model does
            height = round(height / self.patch) * self.patch
            width = round(width / self.patch) * self.patch
            images = TF.resize(images, [height, width], antialias=True)
        tokens = vit_tokens(self.backbone, images, final_norm=True)
        return F.normalize(self.aggregator(patch_map(tokens, height, width, self.patch), tokens[:, 0]), dim=-1)


def read_weights(weights, cache_dir=None) -> tuple[dict, dict]:
    """(state dict, identity) from a local .safetensors/.pth file or the released file."""
    checkpoint, identity = load_checkpoint(weights, WEIGHTS, METHOD, cache_dir)
    return state_dict_of(checkpoint), identity


def build(
    config: MegaLocConfig, *, weights=None, resize=None, batch_size=None, precision="fp32", device="cpu",
    cache_dir=None,
) -> TorchMethod:
    """A MegaLoc method for `config` (the published one, or a reduced one in tests)."""
    resize = as_resize(resize)
    state, identity = read_weights(weights, cache_dir)
    model = MegaLoc(config)
    load_exact(model, state, METHOD)
    fingerprint = {
        "method": METHOD,
        **identity,
        "backbone": "dinov2_vitb14" if config == MegaLocConfig() else repr(config),
        "dim": config.dim,
    }
    # As the authors' evaluation: normalise, then the optional resize (bilinear, antialiased).
    preprocess = Preprocess(resize=resize, interpolation="bilinear", normalise_first=True)
    return TorchMethod(
        model, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision, dim=config.dim
    )


def megaloc(
    backbone="dinov2_vitb14", weights=None, resize=None, batch_size=None, precision="fp32", device="cpu", dim=None,
    cache_dir=None,
):
    choose("backbone", backbone, list(BACKBONES), METHOD)
    config = MegaLocConfig()
    check_dim(METHOD, dim, [config.dim], "dinov2_vitb14")
    return build(config, weights=weights, resize=resize, batch_size=batch_size, precision=precision, device=device,
                 cache_dir=cache_dir)

#: unset resize is the image as stored: resize=native written out is the same run
megaloc.implied_options = native_when_unset
