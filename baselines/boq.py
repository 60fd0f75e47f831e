"""BoQ, Bag-of-Queries (Ali-bey et al., CVPR 2024): learnt queries cross-attending to local features.

Two released models, matched parameter for parameter (`backbone.*`, `aggregator.*`):
- ResNet-50 cut after layer3 (1024 channels), 512-D projection -> 16384-D, 384x384 input
  (the authors' recommended test size; they train at 320x320);
- DINOv2 ViT-B/14 (all blocks, no final norm, CLS dropped), 384-D projection -> 12288-D,
  322x322 input.
Preprocessing as the authors': ToTensor, bicubic antialiased resize, ImageNet normalisation.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError

from .common import Preprocess, TorchMethod, WeightSource, as_int, as_resize, load_checkpoint, load_exact, state_dict_of
from .salad import official_to_model
from .vit import DINOV2_VITB14, ViTConfig, check_patch_multiple, dinov2_vit, patch_map, vit_tokens

METHOD = "boq"
_RELEASE = "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/"


class BoQBlock(nn.Module):
    def __init__(self, dim: int, queries: int, heads: int):
        super().__init__()
        self.encoder = nn.TransformerEncoderLayer(
            d_model=dim, nhead=heads, dim_feedforward=4 * dim, batch_first=True, dropout=0.0
        )
        self.queries = nn.Parameter(torch.randn(1, queries, dim))
        # Self-attention among the queries: input-independent, kept because the weights hold it.
        self.self_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, num_heads=heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.encoder(x)
        q = self.queries.expand(x.shape[0], -1, -1)
        q = self.norm_q(q + self.self_attn(q, q, q, need_weights=False)[0])
        out = self.norm_out(self.cross_attn(q, x, x, need_weights=False)[0])
        return x, out


class BoQAggregator(nn.Module):
    def __init__(self, in_channels: int, proj_channels: int, queries: int = 64, layers: int = 2, row_dim: int = 32):
        super().__init__()
        self.proj_c = nn.Conv2d(in_channels, proj_channels, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.boqs = nn.ModuleList(BoQBlock(proj_channels, queries, proj_channels // 64) for _ in range(layers))
        self.fc = nn.Linear(layers * queries, row_dim)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = self.norm_input(self.proj_c(features).flatten(2).transpose(1, 2))
        outs = []
        for block in self.boqs:
            x, out = block(x)
            outs.append(out)
        out = self.fc(torch.cat(outs, dim=1).transpose(1, 2))  # B, proj_channels, row_dim
        return F.normalize(out.flatten(1), dim=-1)


class ResNet50Trunk(nn.Module):
    """torchvision ResNet-50 up to layer3, as `net.0..6` like the released weights."""

    out_channels = 1024

    def __init__(self):
        super().__init__()
        from torchvision.models import resnet50

        r = resnet50(weights=None)
        self.net = nn.Sequential(r.conv1, r.bn1, r.relu, r.maxpool, r.layer1, r.layer2, r.layer3)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net(images)


class DinoV2Trunk(nn.Module):
    """DINOv2 patch tokens after the last block, without the final norm, as a feature map."""

    def __init__(self, vit: ViTConfig):
        super().__init__()
        self.patch = vit.patch
        self.out_channels = vit.embed_dim
        self.dino = dinov2_vit(vit)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[-2:]
        check_patch_multiple(height, width, self.patch, METHOD)
        return patch_map(vit_tokens(self.dino, images, final_norm=False), height, width, self.patch)


@dataclass(frozen=True)
class BoQConfig:
    backbone: str  # "resnet50" or "dinov2"
    proj_channels: int
    resize: tuple[int, int]
    file_name: str
    vit: ViTConfig = field(default_factory=lambda: DINOV2_VITB14)
    queries: int = 64
    layers: int = 2
    row_dim: int = 32

    @property
    def dim(self) -> int:
        return self.proj_channels * self.row_dim


#: (backbone, output dimension) -> the released model
RELEASED = {
    ("resnet50", 16384): BoQConfig("resnet50", 512, (384, 384), "resnet50_16384.pth"),
    ("dinov2", 12288): BoQConfig("dinov2", 384, (322, 322), "dinov2_12288.pth"),
}


class BoQ(nn.Module):
    def __init__(self, config: BoQConfig):
        super().__init__()
        self.backbone = ResNet50Trunk() if config.backbone == "resnet50" else DinoV2Trunk(config.vit)
        self.aggregator = BoQAggregator(
            self.backbone.out_channels, config.proj_channels, config.queries, config.layers, config.row_dim
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(images))


def build(
    config: BoQConfig, *, weights=None, resize=None, batch_size=None, precision="fp32", device="cpu", cache_dir=None
) -> TorchMethod:
    """A BoQ method for `config` (a released one, or a reduced one in tests)."""
    resize = config.resize if resize is None else as_resize(resize)  # unset: the authors' size; 'native': none
    if config.backbone == "dinov2":
        if resize is None:
            raise VPRBenchError(f"{METHOD}: the DINOv2 backbone takes sides that are multiples of {config.vit.patch}, "
                                "not images as stored: give --resize H W (the authors': "
                                f"{config.resize[0]} {config.resize[1]}).")
        check_patch_multiple(*resize, config.vit.patch, METHOD)
    source = WeightSource(
        config.file_name, url=_RELEASE + config.file_name, page="https://github.com/amaralibey/Bag-of-Queries"
    )
    checkpoint, identity = load_checkpoint(weights, source, METHOD, cache_dir)
    model = BoQ(config)
    load_exact(model, official_to_model(state_dict_of(checkpoint), "backbone.dino."), METHOD)
    released = config in RELEASED.values()
    backbone = config.backbone if released else repr(config)
    fingerprint = {"method": METHOD, **identity, "backbone": backbone, "dim": config.dim}
    # The authors' transform for the released models: ToTensor, bicubic antialiased resize of the
    # float tensor, Normalize (the resize commutes with the normalisation); not a resize of the 8-bit image.
    preprocess = Preprocess(resize=resize, interpolation="bicubic", normalise_first=True)
    return TorchMethod(
        model, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision, dim=config.dim
    )


def boq(backbone="dinov2", dim=None, weights=None, resize=None, batch_size=None, precision="fp32", device="cpu",
        cache_dir=None):
    valid = ", ".join(f"{b} -> {d}" for b, d in RELEASED)
    name = str(backbone).lower()
    dims = [d for b, d in RELEASED if b == name]
    if not dims:
        raise VPRBenchError(f"{METHOD}: unknown backbone {backbone!r}; released backbone/dimension pairs: {valid}.")
    dim = dims[0] if dim is None else as_int(dim, "dim")
    if (name, dim) not in RELEASED:
        raise VPRBenchError(f"{METHOD}: no released model for backbone {name} with dimension {dim}; valid: {valid}.")
    return build(
        RELEASED[name, dim], weights=weights, resize=resize, batch_size=batch_size, precision=precision, device=device,
        cache_dir=cache_dir,
    )
