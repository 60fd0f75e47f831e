"""Image preprocessing exactly as AnyLoc's official extraction scripts do it.

DINOv2 path: ToTensor -> ImageNet mean/std -> optional resize of the *normalised* tensor
(bilinear, align_corners=False, no antialiasing, as the torchvision of 2023 did on
tensors) -> centre crop to the largest multiple of the patch size.
DINO v1 path: ToTensor -> mean/std -> optional resize -> nearest interpolation to 224x298,
no crop.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import VPRBenchError
from ..images import load_rgb

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

def to_normalised_tensor(rgb: np.ndarray, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> torch.Tensor:
    """HxWx3 uint8 -> 3xHxW float32, as ToTensor() then Normalize(mean, std)."""
    x = torch.from_numpy(np.array(rgb, copy=True)).permute(2, 0, 1).float().div(255.0)
    # beside the image, whatever torch.set_default_device a notebook set (a CUDA default failed here)
    mean_t = torch.tensor(mean, dtype=torch.float32, device=x.device).view(3, 1, 1)
    std_t = torch.tensor(std, dtype=torch.float32, device=x.device).view(3, 1, 1)
    return (x - mean_t) / std_t


def resize_tensor(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Bilinear resize of a (3,H,W) tensor without antialiasing (torchvision < 0.17 on tensors)."""
    if tuple(x.shape[-2:]) == tuple(size):
        return x
    return F.interpolate(x[None], size=size, mode="bilinear", align_corners=False, antialias=False)[0]


def crop_offsets(height: int, width: int, patch: int, image: str | Path | None = None) -> tuple[int, int, int, int]:
    """(top, left, new_h, new_w) of the centre crop to multiples of `patch` (of the file `image`, named
    when too small).

    torchvision's CenterCrop uses Python's round(), i.e. half to even: 227 -> 224 starts at row 2.
    """
    new_h, new_w = (height // patch) * patch, (width // patch) * patch
    if new_h == 0 or new_w == 0:
        named = f"Image {image}" if image else "Image"
        raise VPRBenchError(f"{named} of {height}x{width} pixels is smaller than one {patch}x{patch} patch: resize to "
                            f"at least {patch}x{patch} (--resize HEIGHT WIDTH, or the option resize).")
    return round((height - new_h) / 2), round((width - new_w) / 2), new_h, new_w


def centre_crop_to_patches(x: torch.Tensor, patch: int, image: str | Path | None = None) -> torch.Tensor:
    top, left, h, w = crop_offsets(x.shape[-2], x.shape[-1], patch, image)
    return x[..., top:top + h, left:left + w]


def preprocess(path: str | Path, spec, *, resize: tuple[int, int] | None = None) -> torch.Tensor:
    """One image file -> the (3, H, W) tensor the backbone `spec` (a manifest entry) sees."""
    x = to_normalised_tensor(load_rgb(path), spec.mean, spec.std)
    if resize is not None:
        x = resize_tensor(x, resize)
    if spec.resize == "fixed":
        # F.interpolate with the entry's mode (nearest for DINO v1, as the official script calls it)
        return F.interpolate(x[None], size=tuple(spec.input_size), mode=spec.interpolation)[0]
    return centre_crop_to_patches(x, spec.patch, image=path if resize is None else None)
