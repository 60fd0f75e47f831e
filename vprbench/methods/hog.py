"""HOG of the whole resized image (VPR-Bench's HOG baseline settings), compared by cosine."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..errors import VPRBenchError
from ..images import load_rgb
from .base import Method, l2_normalise


class HOG(Method):
    batch_size = 32

    def __init__(self, resize: tuple[int, int] = (512, 512), cell: int = 16, block: int = 16,
                 block_stride: int = 8, bins: int = 9, device: str = "cpu"):
        height, width = (int(v) for v in resize)
        if height < block or width < block or height % block_stride or width % block_stride:
            raise VPRBenchError(f"hog: --resize {height} {width} must be at least {block} and a multiple of {block_stride}")
        self.size = (width, height)
        self.settings = {"resize": [height, width], "cell": cell, "block": block, "block_stride": block_stride, "bins": bins}
        self.hog = cv2.HOGDescriptor(self.size, (block, block), (block_stride, block_stride), (cell, cell), bins)

    def fingerprint(self) -> dict:
        return {**self.settings, "opencv": cv2.__version__.split(".")[0]}

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}  # nothing learnt

    def describe(self, images: Sequence[Path]) -> np.ndarray:
        rows = []
        for path in images:
            # OpenCV order (BGR) as VPR-Bench reads images; HOG takes the strongest channel gradient
            bgr = cv2.resize(load_rgb(path)[:, :, ::-1], self.size, interpolation=cv2.INTER_LINEAR)
            rows.append(self.hog.compute(np.ascontiguousarray(bgr)).reshape(-1))
        return l2_normalise(np.stack(rows))
