"""HOG of the whole resized image (VPR-Bench's HOG baseline settings), compared by cosine."""
from __future__ import annotations

import warnings
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
#: one bin per degree of OpenCV's unsigned 0-180 degree range (more failed inside OpenCV: too large
#: for a C int, or out of memory at the first image)
MAX_BINS = 180
#: OpenCV takes sizes as C ints
MAX_SIDE = 2**31 - 1
#: a window this many times an image's area is said once per run (the protocol's 512 x 512 on thumbnails)
UPSAMPLED_AREA = 16


class HOG(Method):
    batch_size = 32
    device = "cpu"  # OpenCV on the CPU, whatever --device says (checked, then unused): the record says so

    def __init__(self, resize: tuple[int, int] = (512, 512), cell: int = 16, block: int = 16,
                 block_stride: int = 8, bins: int = 9, device: str = "cpu"):
        # OpenCV's own checks are a SIGFPE (cell 0), a SIGSEGV (bins < 4) or an assertion at the first image
        cell, block = whole("hog", "cell", cell, what="pixels per cell side"), whole("hog", "block", block, what="pixels per block side")
        block_stride = whole("hog", "block_stride", block_stride, what="pixels between blocks")
        bins = whole("hog", "bins", bins, MIN_BINS, what="orientation bins")
        # cell and block are bounded by the resize below; these two are not
        if bins > MAX_BINS:
            raise VPRBenchError(f"hog: option bins takes at most {MAX_BINS} orientation bins (one a degree of "
                                f"OpenCV's 0-180 degree range); got {bins}.")
        if block_stride > MAX_SIDE:
            raise VPRBenchError(f"hog: option block_stride takes at most {MAX_SIDE} pixels (OpenCV's limit); got "
                                f"{block_stride}.")
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
        self.hog = self._made()
        self.dataset, self.upsampling_said = None, False

    def _made(self):
        """The HOGDescriptor its parameters make."""
        (height, width), p = self.parameters["resize"], self.parameters
        return cv2.HOGDescriptor((width, height), (p["block"],) * 2, (p["block_stride"],) * 2, (p["cell"],) * 2,
                                 p["bins"])

    def use_dataset(self, name: str) -> None:
        self.dataset = name

    def fingerprint(self) -> dict:
        found = {**self.parameters, "opencv": cv2.__version__.split(".")[0]}
        # what computes the rows, read off the objects doing it: a HOGDescriptor or window set by hand is
        # another descriptor (named only then, so the stores made from the parameters keep their key)
        made, now = _settings(self._made(), self.parameters["resize"][::-1]), _settings(self.hog, self.size)
        if now != made:
            found["descriptor"] = now
        return found

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}  # nothing learnt

    def load(self, path: Path) -> np.ndarray:
        # OpenCV order (BGR) as VPR-Bench reads images; HOG takes the strongest channel gradient
        image = load_rgb(path)
        self._say_upsampling(image.shape[1], image.shape[0])
        return np.ascontiguousarray(cv2.resize(image[:, :, ::-1], self.size, interpolation=cv2.INTER_LINEAR))

    def _say_upsampling(self, width: int, height: int) -> None:
        """Once per run: images far smaller than the window are upsampled to it (the protocol's rule)."""
        (w, h), dims = self.size, self.hog.getDescriptorSize()
        if self.upsampling_said or w * h < UPSAMPLED_AREA * width * height:
            return
        self.upsampling_said = True
        where = f" of {self.dataset}" if self.dataset else ""
        warnings.warn(f"hog: the images{where} ({width} x {height}) are resized to its {w} x {h} window, VPR-Bench's "
                      f"rule: {w * h / (width * height):.0f} times their area, {dims:,} dimensions a descriptor "
                      f"({4 * dims / 1e3:.0f} kB in float32). "
                      f"To describe them near their own size, give --resize (e.g. --resize {self._fit(height)} "
                      f"{self._fit(width)}); its own leaderboard row (docs/methods.md).", stacklevel=2)

    def _fit(self, side: int) -> int:
        """The window side nearest `side` that exceeds the block by a multiple of the block stride."""
        block, stride = self.parameters["block"], self.parameters["block_stride"]
        return block + max(0, round((side - block) / stride)) * stride

    def describe(self, images: Sequence) -> np.ndarray:
        return l2_normalise(np.stack([self.hog.compute(bgr).reshape(-1) for bgr in loaded(self, images)]))


def _settings(hog, size) -> dict:
    """What a HOGDescriptor computes on images resized to `size` (W, H)."""
    found = {k: getattr(hog, k) for k in ("winSize", "blockSize", "blockStride", "cellSize", "nbins", "derivAperture",
                                          "winSigma", "histogramNormType", "L2HysThreshold", "gammaCorrection",
                                          "nlevels", "signedGradient")}
    return {"image": [int(v) for v in size], **{k: list(v) if isinstance(v, tuple) else v for k, v in found.items()}}
