"""NetVLAD (Arandjelovic et al., CVPR 2016) from two public PyTorch releases.

- `netvlad`: the deep-visual-geo-localization benchmark (Berton et al., CVPR 2022) models,
  a ResNet cut after conv4_x (layer3) or VGG16 conv5_3 + NetVLAD with 64 clusters, trained on
  Pitts30k or MSLS. Default: ResNet-18, Pitts30k. Their layer names (`backbone.N`,
  `aggregation.centroids`, `aggregation.conv.weight`).
- `netvlad-vgg16`: the original VGG16 NetVLAD trained with pytorch-NetVlad; the whitening-PCA
  versions (4096/512/128-d) released with Patch-NetVLAD and the full 32768-d one released with
  pytorch-NetVlad. Their layer names (`encoder.N`, `pool.*`, `WPCA.0.*`).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from vprbench import VPRBenchError

from .common import Preprocess, TorchMethod, WeightSource, as_resize, check_dim, choose, build_loaded, load_checkpoint, state_dict_of
from .cosplace import Flatten, L2Norm

CLUSTERS = 64


class NetVLAD(nn.Module):
    """Soft-assignment VLAD: 1x1 conv (no bias) -> softmax over clusters, residuals to
    `centroids`, intra-normalisation, flatten, L2. Inputs are L2-normalised per location."""

    def __init__(self, clusters: int, dim: int):
        super().__init__()
        self.conv = nn.Conv2d(dim, clusters, kernel_size=(1, 1), bias=False)
        self.centroids = nn.Parameter(torch.rand(clusters, dim))

    def forward(self, x):
        x = F.normalize(x, p=2, dim=1)
        assign = F.softmax(self.conv(x).flatten(2), dim=1)  # (N, K, HW)
        features = x.flatten(2)  # (N, D, HW)
        # sum_l a_kl (x_l - c_k) = sum_l a_kl x_l - c_k sum_l a_kl
        vlad = torch.einsum("nkl,ndl->nkd", assign, features) - assign.sum(-1, keepdim=True) * self.centroids
        vlad = F.normalize(vlad, p=2, dim=2)
        return F.normalize(vlad.flatten(1), p=2, dim=1)


# ------------------------------------------------------------ benchmark (dvgl) models
#: backbone -> (channels after the crop, {train set: Google Drive file id})
DVGL_RELEASES = {
    "resnet18conv4": (256, {"pitts30k": "1KFwonDQYdvzTAIILsOMjmLRUR76jXXvB", "msls": "1_Ozq2TdvwLAJUwy7YH9l69GsfOU-MlFZ"}),
    "resnet50conv4": (1024, {"pitts30k": "1KL8HoAApOjJFETin7Q7u7IcsOvroKlSj", "msls": "1krf0A6CeW8GqLqHWZ7dlSNJ9aTJ4dotF"}),
    "resnet101conv4": (1024, {"pitts30k": "1064kDJ0LPyWoU7J4bMvAa0lTNEhAEi8v", "msls": "1rtPfsgfJ2Zoxs5uu7Ph1_qc7q-hIxJek"}),
    "vgg16": (512, {"pitts30k": "14s7OZor6wrlGBKeXr0vKbPfTzlW9preM", "msls": "1dwai3uNudjvns58JIyaf5CBRg4ojcWIW"}),
}
DVGL_ALIASES = {"resnet18": "resnet18conv4", "resnet50": "resnet50conv4", "resnet101": "resnet101conv4"}


def dvgl_backbone(name: str) -> nn.Sequential:
    import torchvision  # here, not at the top: listing methods must not pay for importing it

    if name == "vgg16":
        return nn.Sequential(*list(torchvision.models.vgg16(weights=None).features.children())[:-2])
    resnet = getattr(torchvision.models, name.removesuffix("conv4"))(weights=None)
    return nn.Sequential(*list(resnet.children())[:-3])  # up to layer3 (conv4_x)


class DVGLNetVLAD(nn.Module):
    def __init__(self, backbone: str):
        super().__init__()
        self.backbone = dvgl_backbone(backbone)
        self.aggregation = NetVLAD(CLUSTERS, DVGL_RELEASES[backbone][0])

    def forward(self, x):
        return self.aggregation(self.backbone(x))


def netvlad(
    backbone: str = "resnet18conv4",
    train_set: str = "pitts30k",
    dim: int | str | None = None,
    weights: str | None = None,
    resize=(480, 640),
    batch_size: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    cache_dir=None,
) -> TorchMethod:
    """Benchmark NetVLAD; the descriptor has 64 x backbone-channels dimensions."""
    name = "netvlad"
    backbone = DVGL_ALIASES.get(str(backbone).lower(), backbone)
    valid = ", ".join(f"{b} ({CLUSTERS * c}-d)" for b, (c, _) in DVGL_RELEASES.items())
    try:
        backbone = choose("backbone", backbone, list(DVGL_RELEASES), name)
    except VPRBenchError as error:
        raise VPRBenchError(f"{error} Released: {valid}.") from None
    channels, files = DVGL_RELEASES[backbone]
    train_set = choose("train_set", train_set, list(files), name)
    check_dim(name, dim, [CLUSTERS * channels], backbone)
    source = WeightSource(
        file_name=f"the model zoo's '{backbone.removesuffix('conv4')}-netvlad' {train_set} checkpoint",
        page=f"https://drive.google.com/file/d/{files[train_set]}/view",
    )
    # The benchmark normalises the full image, then resizes the tensor to 480x640 ("hard_resize");
    # its torchvision (0.8) resized tensors without antialiasing. Checked before the weights load.
    preprocess = Preprocess(resize=as_resize(resize), normalise_first=True, antialias=False)
    checkpoint, identity = load_checkpoint(weights, source, name, cache_dir)
    net = build_loaded(lambda: DVGLNetVLAD(backbone), state_dict_of(checkpoint), name)
    fingerprint = {"architecture": "netvlad-dvgl", "backbone": backbone, "dim": CLUSTERS * channels,
                   "clusters": CLUSTERS, "training": train_set, **identity}
    return TorchMethod(net, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision,
                       dim=CLUSTERS * channels)


# ------------------------------------------------------------ original VGG16 NetVLAD
PATCH_NETVLAD_URL = "https://huggingface.co/TobiasRobotics/Patch-NetVLAD/resolve/main/{prefix}_WPCA{dim}.pth.tar"
WPCA_DIMS = (4096, 512, 128)
FULL_DIM = CLUSTERS * 512
PYTORCH_NETVLAD_PAGE = "https://drive.google.com/open?id=17luTjZFCX639guSVy00OUtzfTQo4AMF2"
VGG16_TRAIN_SETS = {"pittsburgh": "pitts", "mapillary": "mapillary"}


class VGG16NetVLAD(nn.Module):
    """VGG16 up to conv5_3 (no ReLU) + NetVLAD, optionally + whitening PCA as a 1x1 conv."""

    def __init__(self, pca_dim: int | None):
        super().__init__()
        self.encoder = dvgl_backbone("vgg16")
        self.pool = NetVLAD(CLUSTERS, 512)
        if pca_dim is not None:
            conv = nn.Conv2d(FULL_DIM, pca_dim, kernel_size=(1, 1))
            self.WPCA = nn.Sequential(conv, Flatten(), L2Norm(dim=-1))

    def forward(self, x):
        vlad = self.pool(self.encoder(x))
        if hasattr(self, "WPCA"):
            return self.WPCA(vlad[:, :, None, None])
        return vlad


def netvlad_vgg16(
    train_set: str = "pittsburgh",
    dim: int | str = 4096,
    weights: str | None = None,
    resize=None,
    batch_size: int | None = None,
    device: str = "cpu",
    precision: str = "fp32",
    cache_dir=None,
) -> TorchMethod:
    """Original VGG16 NetVLAD: WPCA 4096/512/128-d (Patch-NetVLAD release) or full 32768-d (pytorch-NetVlad)."""
    name = "netvlad-vgg16"
    dim = check_dim(name, dim, [*WPCA_DIMS, FULL_DIM], "VGG16 NetVLAD")
    train_set = choose("train_set", train_set, list(VGG16_TRAIN_SETS), name)
    if dim == FULL_DIM:
        if train_set != "pittsburgh":
            raise VPRBenchError(f"{name}: the {FULL_DIM}-d model is released for pittsburgh only.")
        source = WeightSource("vgg16_netvlad_checkpoint/checkpoints/model_best.pth.tar", page=PYTORCH_NETVLAD_PAGE)
        default_resize = None  # pytorch-NetVlad evaluates Pitts30k at full resolution
    else:
        prefix = VGG16_TRAIN_SETS[train_set]
        url = PATCH_NETVLAD_URL.format(prefix=prefix, dim=dim)
        # Patch-NetVLAD's download script saves the pitts_ files as pittsburgh_
        source = WeightSource(f"{prefix}_WPCA{dim}.pth.tar", url=url, also_named=(f"{train_set}_WPCA{dim}.pth.tar",))
        default_resize = (480, 640)  # Patch-NetVLAD's feature-extraction configs
    resize = as_resize(resize) if resize is not None else default_resize
    checkpoint, identity = load_checkpoint(weights, source, name, cache_dir)
    pca_dim = None if dim == FULL_DIM else dim
    net = build_loaded(lambda: VGG16NetVLAD(pca_dim), state_dict_of(checkpoint), name)
    preprocess = Preprocess(resize=resize)  # torchvision Resize on the PIL image, then ImageNet normalisation
    fingerprint = {"architecture": name, "backbone": "vgg16", "dim": dim, "clusters": CLUSTERS,
                   "training": train_set, **identity}
    return TorchMethod(net, preprocess, fingerprint, batch_size=batch_size, device=device, precision=precision, dim=dim)


def _vgg16_resize(options: dict) -> dict:
    """netvlad_vgg16's `implied_options`: the size an unset resize stands for (full resolution for the
    32768-d model, Patch-NetVLAD's 480 x 640 for the WPCA ones), so writing it out is the same run."""
    try:
        full = int(options.get("dim", 4096)) == FULL_DIM
    except (TypeError, ValueError):  # a bad dim: the factory names it
        return {}
    return {"resize": "native" if full else [480, 640]}


netvlad_vgg16.implied_options = _vgg16_resize
