"""The DINOv2 ViT trunk shared by SALAD, BoQ and MegaLoc (timm layers, official token path).

The VPR methods fine-tune DINOv2 and ship the backbone inside their own checkpoint, so
only the architecture is needed here: timm's VisionTransformer has the official DINOv2
parameter names (minus the unused `mask_token`). Position embeddings are resampled the
way the official code does it, which timm's own resampling does not match.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError


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


def interpolate_pos_embed(pos_embed: torch.Tensor, grid: tuple[int, int]) -> torch.Tensor:
    """Official DINOv2 resampling of (1, 1 + M*M, C) embeddings to a (rows, cols) patch grid.

    Bicubic, no antialiasing, driven by scale_factor = (grid + 0.1) / M (so the sampling
    grid differs from a plain resize to `grid`); untouched for a square M x M grid.
    """
    m = int(round((pos_embed.shape[1] - 1) ** 0.5))
    if grid == (m, m):
        return pos_embed
    dtype = pos_embed.dtype
    cls_pos, patch_pos = pos_embed[:, :1].float(), pos_embed[:, 1:].float()
    dim = pos_embed.shape[-1]
    patch_pos = F.interpolate(
        patch_pos.reshape(1, m, m, dim).permute(0, 3, 1, 2),
        scale_factor=((grid[0] + 0.1) / m, (grid[1] + 0.1) / m),
        mode="bicubic",
        antialias=False,
    )
    if tuple(patch_pos.shape[-2:]) != tuple(grid):  # the +0.1 offset exists to prevent this
        raise RuntimeError(f"position embedding resampled to {tuple(patch_pos.shape[-2:])}, not {grid}")
    patch_pos = patch_pos.permute(0, 2, 3, 1).reshape(1, -1, dim)
    return torch.cat((cls_pos, patch_pos), dim=1).to(dtype)


def check_patch_multiple(height: int, width: int, patch: int, method: str) -> None:
    if height % patch or width % patch:
        raise VPRBenchError(
            f"{method}: input size {height}x{width} is not a multiple of the patch size {patch}; "
            f"choose --resize with both sides multiples of {patch} (e.g. 322 322)."
        )


def vit_tokens(vit: nn.Module, images: torch.Tensor, final_norm: bool) -> torch.Tensor:
    """(B, 1 + rows*cols, C) tokens after every block: [CLS, patches in row-major order]."""
    batch, _, height, width = images.shape
    patch = vit.patch_embed.patch_size[0]
    x = vit.patch_embed(images)
    if x.ndim == 4:  # timm's dynamic-size patch embedding returns B, rows, cols, C
        x = x.flatten(1, 2)
    x = torch.cat((vit.cls_token.expand(batch, -1, -1), x), dim=1)
    x = x + interpolate_pos_embed(vit.pos_embed, (height // patch, width // patch))
    for block in vit.blocks:
        x = block(x)
    return vit.norm(x) if final_norm else x


def patch_map(tokens: torch.Tensor, height: int, width: int, patch: int) -> torch.Tensor:
    """Patch tokens (CLS dropped) as a (B, C, rows, cols) feature map."""
    batch, _, channels = tokens.shape
    return tokens[:, 1:].reshape(batch, height // patch, width // patch, channels).permute(0, 3, 1, 2)
