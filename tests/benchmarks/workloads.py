"""AnyLoc pipeline workloads for the benchmarks, and a peak-memory probe.

`python tests/benchmarks/workloads.py NAME` runs one workload in a fresh process and prints
its peak resident memory above the process's footprint after setup (imports, inputs,
model), as JSON. Peak RSS covers torch's and numpy's allocations alike (tracemalloc
would miss torch's CPU allocator). The kernel's peak counter is reset after setup
through /proc/self/clear_refs.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np
import timm
import torch
import torch.nn.functional as F

from vprbench.aggregation import fit_vocabulary, vlad_hard

IMAGE_SIZE = 224          # ViT-S/14 at 224x224: 16x16 = 256 patches of 384 dims
LAYER = 11                # last block of ViT-S, value facet (the authors' script defaults)
CLUSTERS = 32


def vit_small(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)  # random init: no pretrained weights on this machine
    return timm.create_model("vit_small_patch14_dinov2", pretrained=False, img_size=IMAGE_SIZE).eval()


@torch.no_grad()
def value_facet(model, images: torch.Tensor, layer: int = LAYER) -> torch.Tensor:
    """(B, 3, H, W) -> (B, patches, 384) L2-normalised value facet of block `layer`, CLS dropped."""
    x = model._pos_embed(model.patch_embed(images))
    for block in model.blocks[:layer]:
        x = block(x)
    block = model.blocks[layer]
    dim = x.shape[-1]
    qkv = block.attn.qkv(block.norm1(x))
    return F.normalize(qkv[:, 1:, 2 * dim:], dim=-1)


def images(n: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(n, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(seed))


def patch_features(n_images: int, n_patches: int, dim: int, seed: int = 0) -> torch.Tensor:
    """Clustered unit vectors shaped like patch features: (n_images, n_patches, dim)."""
    g = torch.Generator().manual_seed(seed)
    modes = torch.randn(64, dim, generator=g)
    pick = torch.randint(0, 64, (n_images, n_patches), generator=g)
    return F.normalize(modes[pick] + 0.8 * torch.randn(n_images, n_patches, dim, generator=g), dim=-1)


def feature_stream(n_images: int, n_patches: int = 256, dim: int = 384):
    """Per-image patch features generated on demand, as an extractor would yield them."""
    modes = torch.randn(64, dim, generator=torch.Generator().manual_seed(0))
    for i in range(n_images):
        g = torch.Generator().manual_seed(1000 + i)
        pick = torch.randint(0, 64, (n_patches,), generator=g)
        yield F.normalize(modes[pick] + 0.8 * torch.randn(n_patches, dim, generator=g), dim=-1)


def naive_vlad(features: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """The authors' formulation, for comparison: (N, K, D) residuals, then a loop over clusters."""
    a = features / (features.norm(dim=-1, keepdim=True) + 1e-8)
    c = centres / (centres.norm(dim=-1, keepdim=True) + 1e-8)
    labels = (a @ c.T).argmax(dim=-1)
    residuals = features[:, None, :] - centres[None]
    out = torch.zeros(centres.shape[0] * centres.shape[1])
    d = centres.shape[1]
    for k in set(labels.tolist()):
        out[k * d:(k + 1) * d] = F.normalize(residuals[labels == k, k].sum(dim=0), dim=0)
    return F.normalize(out, dim=0)


def centres_for(dim: int) -> torch.Tensor:
    return F.normalize(torch.randn(CLUSTERS, dim, generator=torch.Generator().manual_seed(1)), dim=-1) * 0.6


# name -> (setup() -> state, run(state)); the sizes are what the benchmarks time
VLAD_SHAPES = {"vits": (256, 384), "vitg": (1530, 1536)}  # ViT-G/14 at 476x630: 34x45 patches
FIT_IMAGES, FIT_BUDGET = 600, 20_000  # 153,600 features of 384 dims (236 MB) vs a 20k sample (31 MB)


def workload(name: str):
    if name in ("extract-batch8", "extract-batch1"):
        model, batch = vit_small(), images(8)
        size = 8 if name == "extract-batch8" else 1
        return lambda: [value_facet(model, batch[i:i + size]) for i in range(0, 8, size)]
    kind, _, shape = name.rpartition("-")
    if kind in ("vlad-ours", "vlad-naive"):
        n, d = VLAD_SHAPES[shape]
        feats, centres = patch_features(8, n, d), centres_for(d)
        if kind == "vlad-ours":
            return lambda: [vlad_hard(f, centres) for f in feats]
        return lambda: [naive_vlad(f, centres) for f in feats]
    if name in ("fit-sampled", "fit-exact"):
        exact = name == "fit-exact"
        return lambda: fit_vocabulary(feature_stream(FIT_IMAGES), CLUSTERS, exact=exact, budget=FIT_BUDGET)
    raise SystemExit(f"unknown workload {name}")


def _rss_kb(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def probe(name: str) -> dict:
    run = workload(name)
    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")  # reset the peak-RSS counter (VmHWM) to the current RSS
    base = _rss_kb("VmRSS:")
    start = time.perf_counter()
    run()
    seconds = time.perf_counter() - start
    return {"workload": name, "peak_extra_mb": round((_rss_kb("VmHWM:") - base) / 1024, 1),
            "baseline_mb": round(base / 1024, 1), "seconds_once": round(seconds, 3)}


if __name__ == "__main__":
    torch.set_num_threads(int(sys.argv[2]) if len(sys.argv) > 2 else torch.get_num_threads())
    print(json.dumps(probe(sys.argv[1])))
