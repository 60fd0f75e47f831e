"""AnyLoc pipeline workloads for the benchmarks, and a peak-memory probe.

`python tests/benchmarks/workloads.py NAME` runs one workload in a fresh process and prints
its peak resident memory above the process's footprint after setup (imports, inputs,
model), as JSON. Peak RSS covers torch's and numpy's allocations alike (tracemalloc
would miss torch's CPU allocator). The kernel's peak counter is reset after setup
through /proc/self/clear_refs.
"""
from __future__ import annotations

import atexit
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

import vprbench
from vprbench.aggregation import fit_vocabulary, vlad_hard
from vprbench.features.backbones import backbone_spec, create_model
from memory import measured  # this folder is on sys.path (as a script and under pytest)

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/, for the release layouts
from release_formats import official_state_dict  # noqa: E402

IMAGE_SIZE = 224          # ViT-S/14 at 224x224: 16x16 = 256 patches of 384 dims
LAYER = 9                 # value facet of block 9 of ViT-S/14
CLUSTERS = 32
EXTRACT_IMAGES = 8


def extraction_inputs(folder: Path) -> tuple[Path, list[Path]]:
    """A random ViT-S/14 in the official checkpoint format (no pretrained weights on this
    machine) and 8 random 224x224 PNGs, written to `folder`."""
    torch.manual_seed(0)
    spec = backbone_spec("dinov2_vits14")
    weights = folder / "dinov2_vits14_pretrain.pth"
    torch.save(official_state_dict(create_model(spec), spec), weights)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(EXTRACT_IMAGES):
        path = folder / f"{i:02d}.png"
        Image.fromarray(rng.integers(0, 256, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)).save(path)
        paths.append(path)
    return weights, paths


def anyloc_describe(batch_size: int):
    """vprbench's own path: create_method + describe (file reading, preprocessing, backbone,
    value facet, GeM), the model loaded during setup as a long run would have it."""
    folder = Path(tempfile.mkdtemp(prefix="vprbench-bench-"))
    atexit.register(shutil.rmtree, folder, ignore_errors=True)
    weights, paths = extraction_inputs(folder)
    method = vprbench.create_method("anyloc-vlad-dinov2", backbone="dinov2_vits14", weights=str(weights),
                                    layer=LAYER, facet="value", aggregation="gem", batch_size=batch_size)
    method.extractor  # load the backbone now, not inside the timed run
    return lambda: method.describe(paths)


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
    if name in ("extract-anyloc-batch8", "extract-anyloc-batch1"):
        return anyloc_describe(int(name.removeprefix("extract-anyloc-batch")))
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


def probe(name: str) -> dict:
    _, seconds, base, peak = measured(workload(name))
    return {"workload": name, "peak_extra_mb": round((peak - base) / 1024, 1),
            "baseline_mb": round(base / 1024, 1), "seconds_once": round(seconds, 3)}


if __name__ == "__main__":
    torch.set_num_threads(int(sys.argv[2]) if len(sys.argv) > 2 else torch.get_num_threads())
    print(json.dumps(probe(sys.argv[1])))
