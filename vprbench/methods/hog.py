"""HOG of the whole resized image (VPR-Bench's HOG baseline settings), compared by cosine."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..errors import VPRBenchError
from ..features.resize import parse_size
from ..images import load_rgb
from ..loader import loaded
from .base import Method, l2_normalise
from .checks import whole

#: OpenCV's HOG crashes (SIGSEGV) with fewer orientation bins
MIN_BINS = 4


class HOG(Method):
    batch_size = 32

    def __init__(self, resize: tuple[int, int] = (512, 512), cell: int = 16, block: int = 16,
                 block_stride: int = 8, bins: int = 9, device: str = "cpu"):
        # OpenCV's own checks are a SIGFPE (cell 0), a SIGSEGV (bins < 4) or an assertion at the first image
        cell, block = whole("hog", "cell", cell, what="pixels per cell side"), whole("hog", "block", block, what="pixels per block side")
        block_stride = whole("hog", "block_stride", block_stride, what="pixels between blocks")
        bins = whole("hog", "bins", bins, MIN_BINS, what="orientation bins")
        if block % cell:
            raise VPRBenchError(f"hog: option block ({block}) must be a multiple of cell ({cell}).")
        size = parse_size(resize)
        if size is None:
            raise VPRBenchError("hog: option resize takes the size HOG is computed at, H W (e.g. 512 512); got none.")
        height, width = size
        if height < block or width < block or (height - block) % block_stride or (width - block) % block_stride:
            raise VPRBenchError(f"hog: --resize {height} {width} must be at least the block ({block}) and exceed it "
                                f"by a multiple of block_stride ({block_stride}), e.g. {block + 8 * block_stride} {block + 8 * block_stride}.")
        self.size = (width, height)
        self.parameters = {"resize": [height, width], "cell": cell, "block": block, "block_stride": block_stride, "bins": bins}
        self.hog = cv2.HOGDescriptor(self.size, (block, block), (block_stride, block_stride), (cell, cell), bins)

    def fingerprint(self) -> dict:
        return {**self.parameters, "opencv": cv2.__version__.split(".")[0]}

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}  # nothing learnt

    def load(self, path: Path) -> np.ndarray:
        # OpenCV order (BGR) as VPR-Bench reads images; HOG takes the strongest channel gradient
        return np.ascontiguousarray(cv2.resize(load_rgb(path)[:, :, ::-1], self.size, interpolation=cv2.INTER_LINEAR))

    def describe(self, images: Sequence) -> np.ndarray:
        return l2_normalise(np.stack([self.hog.compute(bgr).reshape(-1) for bgr in loaded(self, images)]))
