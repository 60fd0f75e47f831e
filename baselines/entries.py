"""Entry points of the `vprbench.methods` and `vprbench.stages` groups: each baseline registered by the
import path of its factory or stage class, so listing methods or stages imports no baseline (nor torch)
until one is built."""
from __future__ import annotations

from vprbench import register_method


def netvlad() -> None:
    """Entry point of the `vprbench.methods` group."""
    register_method(
        "netvlad",
        "vprbench_baselines.netvlad:netvlad",
        defaults={"backbone": "resnet18conv4", "train_set": "pitts30k"},
        description="NetVLAD, ResNet-18 (to conv4) + 64 clusters, 16384-d, trained on Pitts30k "
        "(deep-visual-geo-localization benchmark); --backbone resnet50conv4|resnet101conv4|vgg16, -o train_set=msls.",
    )
    register_method(
        "netvlad-vgg16",
        "vprbench_baselines.netvlad:netvlad_vgg16",
        defaults={"train_set": "pittsburgh", "dim": 4096},
        description="Original VGG16 NetVLAD + whitening PCA 4096-d (Patch-NetVLAD release, Pitts30k); "
        "-o dim=512|128|32768, -o train_set=mapillary.",
    )


def cosplace() -> None:
    """Entry point of the `vprbench.methods` group."""
    register_method(
        "cosplace",
        "vprbench_baselines.cosplace:cosplace",
        defaults={"backbone": "ResNet101", "dim": 2048},
        description="CosPlace (CVPR 2022), ResNet-101 GeM+FC 2048-d trained on SF-XL; "
        "-o dim=N and --backbone pick other released models.",
    )


def eigenplaces() -> None:
    """Entry point of the `vprbench.methods` group."""
    register_method(
        "eigenplaces",
        "vprbench_baselines.eigenplaces:eigenplaces",
        defaults={"backbone": "ResNet50", "dim": 2048},
        description="EigenPlaces (ICCV 2023), ResNet-50 GeM+FC 2048-d trained on SF-XL; "
        "-o dim=N and --backbone pick other released models.",
    )


def mixvpr() -> None:
    """Entry point of the `vprbench.methods` group."""
    register_method(
        "mixvpr",
        "vprbench_baselines.mixvpr:mixvpr",
        defaults={"backbone": "resnet50", "dim": 4096},
        description="MixVPR (WACV 2023), ResNet-50 + feature mixer, 4096-d, 320x320 input, trained on GSV-Cities.",
    )


def clip() -> None:
    register_method(
        "clip-cls",
        "vprbench_baselines.clip:clip_cls",
        defaults={"backbone": "ViT-bigG-14", "pretrained": "laion2b_s39b_b160k"},
        description="CLIP baseline of AnyLoc: OpenCLIP ViT-bigG-14 (LAION-2B) image embedding, 1280-D.",
    )


def salad() -> None:
    register_method(
        "salad",
        "vprbench_baselines.salad:salad",
        defaults={"backbone": "dinov2_vitb14", "resize": (322, 322)},
        description="SALAD (CVPR 2024): DINOv2 ViT-B/14 + optimal-transport aggregation, 8448-D, 322x322 input.",
    )


def boq() -> None:
    register_method(
        "boq-dinov2",
        "vprbench_baselines.boq:boq",
        defaults={"backbone": "dinov2"},
        description="BoQ (CVPR 2024) on DINOv2 ViT-B/14: 12288-D, 322x322 input.",
    )
    register_method(
        "boq-resnet50",
        "vprbench_baselines.boq:boq",
        defaults={"backbone": "resnet50"},
        description="BoQ (CVPR 2024) on ResNet-50: 16384-D, 384x384 input.",
    )


def megaloc() -> None:
    register_method(
        "megaloc",
        "vprbench_baselines.megaloc:megaloc",
        defaults={"backbone": "dinov2_vitb14"},
        description="MegaLoc (CVPRW 2025): DINOv2 ViT-B/14 + SALAD-style aggregation, 8448-D, full-resolution input.",
    )


def superpoint_lightglue() -> None:
    """Entry point of the `vprbench.stages` group: a learned re-ranker, registered as a third-party stage is."""
    from vprbench.stages import register_stage

    register_stage(
        "superpoint-lightglue",
        "vprbench_baselines.lightglue:SuperPointLightGlue",
        description="SuperPoint keypoints matched by LightGlue (kornia); score = matches, or their RANSAC inliers "
        "(model=fundamental|homography); the authors' weights, a folder of them, or weights=random",
    )
