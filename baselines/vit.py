"""The DINOv2 ViT trunk shared by SALAD, BoQ and MegaLoc (timm layers, official token path).

The VPR methods fine-tune DINOv2 and ship the backbone inside their own checkpoint, so
only the architecture is needed here: timm's VisionTransformer has the official DINOv2
parameter names (minus the unused `mask_token`). Tokens come from vprbench's one dense
extractor (features/dense.py), which resamples position embeddings with the official DINOv2
interpolation (timm's own resampling does not match it).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vprbench import VPRBenchError
from vprbench.features.catalogue import backbone_spec
from vprbench.features.dense import DenseExtractor


@dataclass(frozen=True)
class ViTConfig:
    """A DINOv2 ViT. The released VPR models all use ViT-B/14 (`DINOV2_VITB14`)."""

    embed_dim: int = 768
    depth: int = 12
    heads: int = 12
    patch: int = 14
    #: the size DINOv2 was trained at: 37 x 37 position embeddings
    img_size: int = 518


DINOV2_VITB14 = ViTConfig()


def dinov2_vit(config: ViTConfig = DINOV2_VITB14) -> nn.Module:
    """Random-initialised DINOv2-style ViT without a classifier head."""
    from timm.models.vision_transformer import VisionTransformer

    return VisionTransformer(
        img_size=config.img_size,
        patch_size=config.patch,
        embed_dim=config.embed_dim,
        depth=config.depth,
        num_heads=config.heads,
        init_values=1e-5,  # LayerScale: gives the ls1/ls2.gamma parameters
        num_classes=0,
        dynamic_img_size=True,  # accept any multiple of the patch size
    )


def check_patch_multiple(height: int, width: int, patch: int, method: str) -> None:
    if height % patch or width % patch:
        raise VPRBenchError(
            f"{method}: input size {height}x{width} is not a multiple of the patch size {patch}; "
            f"choose --resize with both sides multiples of {patch} (e.g. 322 322)."
        )


def vit_tokens(vit: nn.Module, images: torch.Tensor, final_norm: bool) -> torch.Tensor:
    """(B, 1 + rows*cols, C) tokens after every block: [CLS, patches in row-major order]."""
    # the DINOv2 entry's token path, at this trunk's patch size (tests build tiny trunks)
    spec = backbone_spec("dinov2_vitb14").model_copy(update={"patch": vit.patch_embed.patch_size[0]})
    tokens = DenseExtractor(vit, spec, len(vit.blocks) - 1, "token")(images, keep_prefix=True)
    return vit.norm(tokens) if final_norm else tokens


def patch_map(tokens: torch.Tensor, height: int, width: int, patch: int) -> torch.Tensor:
    """Patch tokens (CLS dropped) as a (B, C, rows, cols) feature map."""
    batch, _, channels = tokens.shape
    return tokens[:, 1:].reshape(batch, height // patch, width // patch, channels).permute(0, 3, 1, 2)
