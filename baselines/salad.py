"""SALAD (Izquierdo & Civera, CVPR 2024): DINOv2 ViT-B/14 + optimal-transport aggregation.

Matches the authors' released `dino_salad.ckpt` (parameter names `backbone.model.*`,
`aggregator.*`) and their evaluation: 322x322 bilinear resize, ImageNet normalisation,
final-norm tokens, CLS -> global token, patches -> 64 clusters x 128 dims, 8448 in all.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError
from vprbench.images import load_image

from .common import (
    Preprocess,
    TorchMethod,
    WeightSource,
    as_resize,
    check_dim,
    choose,
    load_checkpoint,
    load_exact,
    state_dict_of,
)
from .vit import DINOV2_VITB14, ViTConfig, check_patch_multiple, dinov2_vit, patch_map, vit_tokens

METHOD = "salad"
WEIGHTS = WeightSource(
    "dino_salad.ckpt",
    url="https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt",
    page="https://github.com/serizba/salad",
)
#: backbone name -> feature channels; the authors released weights for ViT-B/14 only
BACKBONES = {"dinov2_vitb14": 768}


# ---------------------------------------------------------------- optimal transport
def sinkhorn_log_assignment(scores: torch.Tensor, dustbin: torch.Tensor, iterations: int = 3) -> torch.Tensor:
    """log P for (B, clusters, patches) scores with a dustbin row, by log-domain Sinkhorn.

    Row masses are 1/(n+m) for each cluster and (n-m)/(n+m) for the dustbin, column masses
    1/(n+m); the result is rescaled so each patch distributes a total mass of one.
    """
    batch, m, n = scores.shape
    if n <= m:
        raise VPRBenchError(
            f"SALAD aggregation needs more patches ({n}) than clusters ({m}); use a larger --resize."
        )
    augmented = torch.cat([scores, dustbin.to(scores.dtype).expand(batch, 1, n)], dim=1)
    norm = -math.log(n + m)
    log_a = torch.full((batch, m + 1), norm, dtype=scores.dtype, device=scores.device)
    log_a[:, -1] += math.log(n - m)
    log_b = torch.full((batch, n), norm, dtype=scores.dtype, device=scores.device)
    u, v = torch.zeros_like(log_a), torch.zeros_like(log_b)
    for _ in range(iterations):
        u = log_a - torch.logsumexp(augmented + v.unsqueeze(1), dim=2)
        v = log_b - torch.logsumexp(augmented + u.unsqueeze(2), dim=1)
    return augmented + u.unsqueeze(2) + v.unsqueeze(1) - norm


class SaladAggregator(nn.Module):
    """Token MLP, per-patch cluster features and scores, Sinkhorn assignment, intra-norm.

    Layer names and order follow the released checkpoints (dropout sits at index 1 of the
    convolutional MLPs and holds no parameters).
    """

    def __init__(
        self, channels: int, clusters: int = 64, cluster_dim: int = 128, token_dim: int = 256, hidden: int = 512
    ):
        super().__init__()
        self.clusters, self.cluster_dim = clusters, cluster_dim
        self.token_features = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(), nn.Linear(hidden, token_dim))
        self.cluster_features = nn.Sequential(
            nn.Conv2d(channels, hidden, 1), nn.Dropout(0.3), nn.ReLU(), nn.Conv2d(hidden, cluster_dim, 1)
        )
        self.score = nn.Sequential(
            nn.Conv2d(channels, hidden, 1), nn.Dropout(0.3), nn.ReLU(), nn.Conv2d(hidden, clusters, 1)
        )
        self.dust_bin = nn.Parameter(torch.tensor(1.0))

    def forward(self, features: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
        local = self.cluster_features(features).flatten(2)  # B, cluster_dim, patches
        scores = self.score(features).flatten(2)  # B, clusters, patches
        assignment = sinkhorn_log_assignment(scores, self.dust_bin).exp()[:, :-1]  # dustbin dropped
        aggregated = torch.einsum("bln,bmn->blm", local, assignment)  # B, cluster_dim, clusters
        descriptor = torch.cat(
            [F.normalize(self.token_features(token), dim=-1), F.normalize(aggregated, dim=1).flatten(1)], dim=-1
        )
        return F.normalize(descriptor, dim=-1)


@dataclass(frozen=True)
class SaladConfig:
    vit: ViTConfig = field(default_factory=lambda: DINOV2_VITB14)
    clusters: int = 64
    cluster_dim: int = 128
    token_dim: int = 256

    @property
    def dim(self) -> int:
        return self.clusters * self.cluster_dim + self.token_dim


class Salad(nn.Module):
    def __init__(self, config: SaladConfig = SaladConfig()):
        super().__init__()
        self.patch = config.vit.patch
        self.backbone = nn.Module()  # the authors wrap the hub DINOv2 as backbone.model
        self.backbone.model = dinov2_vit(config.vit)
        self.aggregator = SaladAggregator(config.vit.embed_dim, config.clusters, config.cluster_dim, config.token_dim)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[-2:]
        check_patch_multiple(height, width, self.patch, METHOD)
        tokens = vit_tokens(self.backbone.model, images, final_norm=True)
        return self.aggregator(patch_map(tokens, height, width, self.patch), tokens[:, 0])


class PilResize(Preprocess):
    """The authors' eval transform: PIL bilinear resize of the 8-bit image, ToTensor, normalise."""

    def __call__(self, path: Path) -> torch.Tensor:
        from PIL import Image
        from torchvision.transforms import functional as TF

        image = load_image(path, "RGB")
        if self.resize is not None:
            image = image.resize((self.resize[1], self.resize[0]), Image.BILINEAR)
        return TF.normalize(TF.to_tensor(image), self.mean, self.std)

    def fingerprint(self) -> dict:
        return {**super().fingerprint(), "resize_on": "8-bit image (PIL)"}


def official_to_model(state: dict, prefix: str) -> dict:
    """The released files keep DINOv2's unused mask_token; timm's ViT has none."""
    return {k: v for k, v in state.items() if k != f"{prefix}mask_token"}


def build(
    config: SaladConfig, *, weights=None, resize=(322, 322), batch_size=None, precision="fp32", device="cpu",
    cache_dir=None,
) -> TorchMethod:
    """A SALAD method for `config` (the published one, or a reduced one in tests)."""
    resize = as_resize(resize)
    if resize is not None:
        check_patch_multiple(*resize, config.vit.patch, METHOD)
    checkpoint, identity = load_checkpoint(weights, WEIGHTS, METHOD, cache_dir)
    model = Salad(config)
    load_exact(model, official_to_model(state_dict_of(checkpoint), "backbone.model."), METHOD)
    fingerprint = {
        "method": METHOD,
        **identity,
        "backbone": "dinov2_vitb14" if config == SaladConfig() else repr(config),
        "dim": config.dim,
    }
    preprocess = PilResize(resize=resize, interpolation="bilinear")
    return TorchMethod(
        model, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision, dim=config.dim
    )


def salad(
    backbone="dinov2_vitb14", weights=None, resize=(322, 322), batch_size=None, precision="fp32", device="cpu", dim=None,
    cache_dir=None,
):
    choose("backbone", backbone, list(BACKBONES), METHOD)
    config = SaladConfig()
    check_dim(METHOD, dim, [config.dim], "dinov2_vitb14")
    return build(config, weights=weights, resize=resize, batch_size=batch_size, precision=precision, device=device,
                 cache_dir=cache_dir)
