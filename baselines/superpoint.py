"""SuperPoint (DeTone, Malisiewicz & Rabinovich, CVPRW 2018): keypoints and 256-D descriptors of one image,
as LightGlue's released matcher was trained to take them.

The network has the parameter names of Magic Leap's released `superpoint_v1.pth` (conv1a ... convDb),
so that file loads with no missing or unexpected key. Extraction follows LightGlue's SuperPoint
extractor: the RGB image in [0, 1], its longer side resized to `resize` (kornia, bilinear, antialiased),
made grey (kornia's weights); the detector's 65-way softmax without its "no keypoint" channel laid out
as a full-resolution heatmap; non-maximum suppression over (2r+1)² windows; 4 px borders dropped;
scores above the threshold, the strongest `max_keypoints` kept; descriptors sampled bilinearly from the
coarse map and L2-normalised; keypoints mapped back to the pixels of the image as stored.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

#: cell size of the coarse maps (three 2x2 poolings)
CELL = 8
#: keypoints this close to the border are dropped (LightGlue's SuperPoint default)
BORDER = 4
#: (input, output) channels of the encoder's 3x3 convolutions, in the release's order
ENCODER = {"conv1a": (1, 64), "conv1b": (64, 64), "conv2a": (64, 64), "conv2b": (64, 64),
           "conv3a": (64, 128), "conv3b": (128, 128), "conv4a": (128, 128), "conv4b": (128, 128)}


class SuperPointNet(nn.Module):
    """Shared encoder, detector head (64 positions of a cell + "no keypoint") and descriptor head."""

    def __init__(self):
        super().__init__()
        for name, (given, made) in ENCODER.items():
            setattr(self, name, nn.Conv2d(given, made, 3, padding=1))
        self.convPa = nn.Conv2d(128, 256, 3, padding=1)
        self.convPb = nn.Conv2d(256, 65, 1)
        self.convDa = nn.Conv2d(128, 256, 3, padding=1)
        self.convDb = nn.Conv2d(256, 256, 1)

    def forward(self, grey: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 1, H, W) in [0, 1] -> heatmap (B, H/8*8, W/8*8) and unit descriptors (B, 256, H/8, W/8)."""
        x = grey
        for block in "1234":
            x = F.relu(getattr(self, f"conv{block}b")(F.relu(getattr(self, f"conv{block}a")(x))))
            if block != "4":
                x = F.max_pool2d(x, 2, 2)
        cells = F.softmax(self.convPb(F.relu(self.convPa(x))), dim=1)[:, :-1]
        heatmap = F.pixel_shuffle(cells, CELL)[:, 0]  # channel 8i+j -> pixel (8y+i, 8x+j)
        return heatmap, F.normalize(self.convDb(F.relu(self.convDa(x))), dim=1)


def local_maxima(scores: torch.Tensor, radius: int) -> torch.Tensor:
    """`scores` where they are the maximum of their (2r+1)² window, else 0. Two more rounds keep maxima
    that were only covered by a suppressed neighbour's window (LightGlue's SuperPoint does the same)."""
    def window_max(x):
        return F.max_pool2d(x, 2 * radius + 1, stride=1, padding=radius)

    kept = scores == window_max(scores)
    for _ in range(2):
        covered = window_max(kept.float()) > 0
        rest = torch.where(covered, torch.zeros_like(scores), scores)
        kept = kept | ((rest == window_max(rest)) & ~covered)
    return torch.where(kept, scores, torch.zeros_like(scores))


def sample_descriptors(points: torch.Tensor, coarse: torch.Tensor) -> torch.Tensor:
    """(n, 256) unit descriptors at pixel positions `points` (n, 2) of the resized image, interpolated in
    the coarse map (1, 256, h, w) with LightGlue's SuperPoint mapping: coarse column 0 at pixel 3.5, the
    last at pixel 8w - 1 (rows alike)."""
    _, channels, h, w = coarse.shape
    span = torch.tensor([w * CELL - CELL / 2 - 0.5, h * CELL - CELL / 2 - 0.5]).to(points)
    grid = ((points - CELL / 2 + 0.5) / span) * 2 - 1
    found = F.grid_sample(coarse, grid.view(1, 1, -1, 2), mode="bilinear", align_corners=True)
    return F.normalize(found.reshape(channels, -1), dim=0).T


@torch.inference_mode()
def superpoint_features(net: SuperPointNet, rgb, *, resize: int, max_keypoints: int, threshold: float,
                        nms_radius: int, device: str = "cpu") -> dict:
    """Keypoints `points` (n, 2) float32 (x, y) in the stored image's pixels, `descriptors` (n, 256)
    float32, `size` (2,) the image's (width, height), of one uint8 RGB array (H, W, 3)."""
    from kornia.color import rgb_to_grayscale
    from kornia.geometry.transform import resize as kornia_resize

    image = torch.tensor(rgb).permute(2, 0, 1)[None].float().div(255).to(device)
    height, width = image.shape[-2:]
    if resize:
        image = kornia_resize(image, resize, side="long", antialias=True)
    scale = torch.tensor([image.shape[-1] / width, image.shape[-2] / height], device=device)
    heatmap, coarse = net(rgb_to_grayscale(image))
    scores = local_maxima(heatmap, nms_radius)[0]
    scores[:BORDER], scores[-BORDER:], scores[:, :BORDER], scores[:, -BORDER:] = -1, -1, -1, -1
    rows, columns = torch.where(scores > threshold)
    strength = scores[rows, columns]
    if len(strength) > max_keypoints:
        strength, best = torch.topk(strength, max_keypoints)
        rows, columns = rows[best], columns[best]
    points = torch.stack([columns, rows], dim=-1).float()
    descriptors = sample_descriptors(points, coarse)
    original = (points + 0.5) / scale - 0.5  # back to the stored image's pixels, as LightGlue's extractor
    return {"points": original.float().cpu().numpy(), "descriptors": descriptors.float().cpu().numpy(),
            "size": torch.tensor([width, height]).numpy()}
