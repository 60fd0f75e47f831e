"""CosPlace (Berton et al., CVPR 2022): CNN backbone, L2 -> GeM -> FC -> L2.

Layer names follow the authors' `GeoLocalizationNet`, so their released
`<Backbone>_<dim>_cosplace.pth` files load exactly. EigenPlaces shares the network.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError

from .common import (TorchMethod, WeightSource, as_int, as_resize, build_loaded, choose, load_checkpoint,
                     native_when_unset, preprocess_for, state_dict_of)

#: backbone -> descriptor dimensions with released weights (authors' hubconf)
RELEASED = {
    "VGG16": (64, 128, 256, 512),
    "ResNet18": (32, 64, 128, 256, 512),
    "ResNet50": (32, 64, 128, 256, 512, 1024, 2048),
    "ResNet101": (32, 64, 128, 256, 512, 1024, 2048),
    "ResNet152": (32, 64, 128, 256, 512, 1024, 2048),
}
#: channels of the last convolutional layer
CHANNELS = {"VGG16": 512, "ResNet18": 512, "ResNet50": 2048, "ResNet101": 2048, "ResNet152": 2048}
RELEASE_URL = "https://github.com/gmberton/CosPlace/releases/download/v1.0/{backbone}_{dim}_cosplace.pth"


class L2Norm(nn.Module):
    def __init__(self, dim: int = 1):
        super().__init__()
        self.dim = dim

    def forward(self, x):
        return F.normalize(x, p=2.0, dim=self.dim)


class GeM(nn.Module):
    """Generalised-mean pooling with a learnt exponent `p` (checkpoint key `...p`)."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.ones(1) * p)
        self.eps = eps

    def forward(self, x):
        return F.avg_pool2d(x.clamp(min=self.eps).pow(self.p), (x.size(-2), x.size(-1))).pow(1.0 / self.p)


class Flatten(nn.Module):
    def forward(self, x):
        return x[:, :, 0, 0]


def conv_backbone(name: str) -> nn.Sequential:
    """torchvision ResNet without avgpool/fc, or VGG16 features without the last ReLU+pool."""
    import torchvision  # here, not at the top: listing methods must not pay for importing it
    model = getattr(torchvision.models, name.lower())(weights=None)
    if name.startswith("ResNet"):
        return nn.Sequential(*list(model.children())[:-2])
    return nn.Sequential(*list(model.features.children())[:-2])


class GeoLocalizationNet(nn.Module):
    def __init__(self, backbone: str, dim: int):
        super().__init__()
        self.backbone = conv_backbone(backbone)
        self.aggregation = nn.Sequential(L2Norm(), GeM(), Flatten(), nn.Linear(CHANNELS[backbone], dim), L2Norm())

    def forward(self, x):
        return self.aggregation(self.backbone(x))


def check_release(method: str, released: dict, backbone, dim) -> tuple[str, int]:
    """Canonical backbone name and int dim, or an error listing the released pairs."""
    valid = "; ".join(f"{b}: {', '.join(map(str, d))}" for b, d in released.items())
    try:
        backbone = choose("backbone", backbone, list(released), method)
    except VPRBenchError as error:
        raise VPRBenchError(f"{error} Released backbone/dimension pairs: {valid}.") from None
    dim = as_int(dim, "dim")
    if dim not in released[backbone]:
        raise VPRBenchError(
            f"{method}: no released weights for {backbone} with dim {dim}; "
            f"{backbone} comes in {', '.join(map(str, released[backbone]))}. All pairs: {valid}."
        )
    return backbone, dim


def build_gem_fc_method(
    method: str, released: dict, url: str, backbone, dim, weights, resize, batch_size, device, precision, training: str,
    cache_dir=None, preprocess: str = "authors",
) -> TorchMethod:
    """Shared by CosPlace and EigenPlaces: same network, different release."""
    backbone, dim = check_release(method, released, backbone, dim)
    file_url = url.format(backbone=backbone, dim=dim)
    source = WeightSource(file_name=file_url.rsplit("/", 1)[1], url=file_url)
    # The authors evaluate at full resolution (ToTensor + ImageNet normalisation, no resize).
    preprocess = preprocess_for(preprocess, method, as_resize(resize))  # checked before the weights load
    checkpoint, identity = load_checkpoint(weights, source, method, cache_dir)
    net = build_loaded(lambda: GeoLocalizationNet(backbone, dim), state_dict_of(checkpoint), method)
    fingerprint = {"architecture": method, "backbone": backbone, "dim": dim, "training": training, **identity}
    return TorchMethod(net, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision, dim=dim)


def cosplace(
    backbone: str = "ResNet101",
    dim: int | str = 2048,
    weights: str | None = None,
    resize=None,
    batch_size: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    cache_dir=None,
    preprocess: str = "authors",
) -> TorchMethod:
    """CosPlace trained on SF-XL; `backbone`/`dim` pick one of the released models; `preprocess=anyloc`
    resizes as AnyLoc's evaluation of it did (normalised tensor, no antialiasing)."""
    return build_gem_fc_method(
        "cosplace", RELEASED, RELEASE_URL, backbone, dim, weights, resize, batch_size, device, precision, "SF-XL CosPlace",
        cache_dir, preprocess,
    )

#: unset resize is the image as stored: resize=native written out is the same run
cosplace.implied_options = native_when_unset
