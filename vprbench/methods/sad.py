"""SeqSLAM's front end (Milford & Wyeth, ICRA 2012), weight-free: the image grey, downsampled
to 64 x 32, each 8 x 8 patch normalised to zero mean and unit deviation, compared by the mean
absolute difference of the pixels (the sum of absolute differences over their number: a
distance, smaller is closer). The sizes are OpenSeqSLAM's defaults (`downsample.size = [32 64]`,
`normalization.sideLength = 8`, `normalization.mode = 1`). OpenSeqSLAM keeps the normalised
patch as 127 + round(z) in a uint8 image; here z stays a float (rounding it to whole numbers
throws most of it away). Resizing is OpenCV's area average (MATLAB's imresize antialiases too).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..errors import VPRBenchError
from ..features.resize import parse_size
from ..images import load_rgb
from ..loader import loaded
from .base import Method
from .checks import whole

#: a patch whose pixels are all equal has no contrast: its values become 0
MIN_DEVIATION = 1e-6


class SAD(Method):
    batch_size = 64
    compare = "mean-absolute-difference"
    device = "cpu"  # numpy on the CPU, whatever --device says (checked, then unused): the record says so

    def __init__(self, resize: tuple[int, int] = (32, 64), patch: int = 8, device: str = "cpu"):
        size = parse_size(resize)
        if size is None:
            raise VPRBenchError("sad: option resize takes the size images are downsampled to, H W (e.g. 32 64); got none.")
        patch = whole("sad", "patch", patch, 2, what="side of the normalised patches, in pixels")
        height, width = size
        if height % patch or width % patch:
            raise VPRBenchError(f"sad: --resize {height} {width} must be a whole number of {patch}-pixel patches "
                                f"(option patch) in each direction, e.g. {patch * max(1, height // patch)} "
                                f"{patch * max(1, width // patch)}.")
        self.size, self.patch = (height, width), patch

    def fingerprint(self) -> dict:
        return {"resize": list(self.size), "patch": self.patch, "grey": "opencv rgb2gray", "resample": "area",
                "opencv": cv2.__version__.split(".")[0]}

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}  # nothing learnt

    def load(self, path: Path) -> np.ndarray:
        grey = cv2.cvtColor(load_rgb(path), cv2.COLOR_RGB2GRAY)
        height, width = self.size
        return cv2.resize(grey, (width, height), interpolation=cv2.INTER_AREA).astype(np.float32)

    def describe(self, images: Sequence) -> np.ndarray:
        return patch_normalise(np.stack(loaded(self, images)), self.patch).reshape(len(images), -1)


def patch_normalise(images: np.ndarray, patch: int) -> np.ndarray:
    """(B, H, W) -> (B, H, W) float32: each patch x patch block minus its mean over its standard
    deviation (n - 1 in the denominator, as MATLAB's std in OpenSeqSLAM)."""
    count, height, width = images.shape
    blocks = images.astype(np.float64).reshape(count, height // patch, patch, width // patch, patch)
    mean = blocks.mean(axis=(2, 4), keepdims=True)
    deviation = blocks.std(axis=(2, 4), ddof=1, keepdims=True)
    normalised = np.where(deviation > MIN_DEVIATION, (blocks - mean) / np.maximum(deviation, MIN_DEVIATION), 0.0)
    return normalised.reshape(count, height, width).astype(np.float32)
