"""MixVPR (Ali-bey et al., WACV 2023): ResNet-50 cropped after layer3 + feature-mixer aggregator.

Layer names follow the authors' `VPRModel` (`backbone.model.*`, `aggregator.*`) so their
released `resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt` loads exactly.
"""
from __future__ import annotations

import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError

from .common import (TorchMethod, WeightSource, as_resize, check_dim, choose, build_loaded, load_checkpoint, preprocess_for,
                     state_dict_of)

#: descriptor dim -> the authors' aggregator settings: out_channels and out_rows as the released
#: files name them (channels(C)_rows(R)); the 4096-d configuration is printed in the README, the
#: others share its mixer (depth 4, ratio 1), as the evaluation code wrapping them builds them
CONFIGS = {
    dim: dict(in_channels=1024, in_h=20, in_w=20, out_channels=channels, mix_depth=4, mlp_ratio=1, out_rows=rows)
    for dim, channels, rows in ((4096, 1024, 4), (512, 256, 2), (128, 64, 2))
}
#: the README's Google Drive files
DRIVE_IDS = {4096: "1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L", 512: "1khiTUNzZhfV2UUupZoIsPIbsMRBYVDqj",
             128: "1DQnefjk1hVICOEYPwE4-CZAZOvi1NSJz"}
WEIGHTS = {
    dim: WeightSource(
        file_name=f"resnet50_MixVPR_{dim}_channels({config['out_channels']})_rows({config['out_rows']}).ckpt",
        page=f"https://drive.google.com/file/d/{DRIVE_IDS[dim]}/view",
    )
    for dim, config in CONFIGS.items()
}
IMAGE_SIZE = (320, 320)


class CroppedResNet(nn.Module):
    """torchvision ResNet-50 without layer4, avgpool and fc (state-dict prefix `model.`)."""

    def __init__(self):
        import torchvision  # here, not at the top: listing methods must not pay for importing it

        super().__init__()
        self.model = torchvision.models.resnet50(weights=None)
        self.model.avgpool = None
        self.model.fc = None
        self.model.layer4 = None

    def forward(self, x):
        m = self.model
        x = m.maxpool(m.relu(m.bn1(m.conv1(x))))
        return m.layer3(m.layer2(m.layer1(x)))


class FeatureMixerLayer(nn.Module):
    def __init__(self, in_dim: int, mlp_ratio: float = 1):
        super().__init__()
        hidden = int(in_dim * mlp_ratio)
        self.mix = nn.Sequential(nn.LayerNorm(in_dim), nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, in_dim))

    def forward(self, x):
        return x + self.mix(x)


class MixVPR(nn.Module):
    """Mixes each channel's flattened HxW map, then projects channels and rows."""

    def __init__(self, in_channels, in_h, in_w, out_channels, mix_depth, mlp_ratio, out_rows):
        super().__init__()
        hw = in_h * in_w
        self.mix = nn.Sequential(*[FeatureMixerLayer(hw, mlp_ratio) for _ in range(mix_depth)])
        self.channel_proj = nn.Linear(in_channels, out_channels)
        self.row_proj = nn.Linear(hw, out_rows)

    def forward(self, x):
        x = self.mix(x.flatten(2))
        x = self.channel_proj(x.permute(0, 2, 1)).permute(0, 2, 1)
        x = self.row_proj(x)
        return F.normalize(x.flatten(1), p=2, dim=-1)


class MixVPRNet(nn.Module):
    def __init__(self, config: dict):
        super().__init__()
        self.backbone = CroppedResNet()
        self.aggregator = MixVPR(**config)

    def forward(self, x):
        return self.aggregator(self.backbone(x))


def mixvpr(
    backbone: str = "resnet50",
    dim: int | str = 4096,
    weights: str | None = None,
    resize=IMAGE_SIZE,
    batch_size: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    cache_dir=None,
    preprocess: str = "authors",
) -> TorchMethod:
    """MixVPR trained on GSV-Cities; images resized to 320x320 (bicubic) as the authors do, or, with
    `preprocess=anyloc`, as AnyLoc's evaluation of it did (bilinear on the normalised tensor)."""
    backbone = choose("backbone", backbone, ["resnet50"], "mixvpr")
    dim = check_dim("mixvpr", dim, list(CONFIGS), "ResNet-50 MixVPR")
    resize = as_resize(resize)
    # The mixer works on a fixed 20x20 map: the input must be 16x that (ResNet stride after layer3).
    config = CONFIGS[dim]
    if resize != (config["in_h"] * 16, config["in_w"] * 16):
        raise VPRBenchError(
            f"mixvpr: resize {resize} does not fit the aggregator's {config['in_h']}x{config['in_w']} "
            f"feature map; valid: {config['in_h'] * 16} {config['in_w'] * 16}."
        )
    preprocessing = preprocess_for(preprocess, "mixvpr", resize, interpolation="bicubic")
    checkpoint, identity = load_checkpoint(weights, WEIGHTS[dim], "mixvpr", cache_dir)
    net = build_loaded(lambda: MixVPRNet(config), state_dict_of(checkpoint), "mixvpr")
    fingerprint = {"architecture": "mixvpr", "backbone": backbone, "dim": dim, "training": "GSV-Cities",
                   "config": config, **identity}
    return TorchMethod(net, preprocessing, fingerprint, batch_size=batch_size, device=device, precision=precision,
                       dim=dim)
