"""EigenPlaces (Berton et al., ICCV 2023): the CosPlace network trained for viewpoint robustness.

The released `<Backbone>_<dim>_eigenplaces.pth` files use the same layer names as
CosPlace's `GeoLocalizationNet`, so the network is shared.
"""
from __future__ import annotations


from .common import TorchMethod, native_when_unset
from .cosplace import build_gem_fc_method

#: backbone -> descriptor dimensions with released weights (authors' hubconf)
RELEASED = {
    "VGG16": (512,),
    "ResNet18": (256, 512),
    "ResNet50": (128, 256, 512, 1024, 2048),
    "ResNet101": (128, 256, 512, 1024, 2048),
}
RELEASE_URL = "https://github.com/gmberton/EigenPlaces/releases/download/v1.0/{backbone}_{dim}_eigenplaces.pth"


def eigenplaces(
    backbone: str = "ResNet50",
    dim: int | str = 2048,
    weights: str | None = None,
    resize=None,
    batch_size: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    cache_dir=None,
) -> TorchMethod:
    """EigenPlaces trained on SF-XL; `backbone`/`dim` pick one of the released models."""
    return build_gem_fc_method(
        "eigenplaces", RELEASED, RELEASE_URL, backbone, dim, weights, resize, batch_size, device, precision,
        "SF-XL EigenPlaces", cache_dir,
    )

#: unset resize is the image as stored: resize=native written out is the same run
eigenplaces.implied_options = native_when_unset
