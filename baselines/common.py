"""Shared pieces of the baselines: weight resolution, exact checkpoint loading,
the authors' preprocessing, and a `Method` that runs a torch model.

Only the public vprbench API is used here, as a third-party plugin would.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from vprbench import Method, VPRBenchError
from vprbench.images import load_image
from vprbench.loader import loaded
from vprbench.methods import l2_normalise
from vprbench.features.resize import parse_size as as_resize  # noqa: F401  (the one resize parser)
from vprbench.weight_source import WeightSource  # noqa: F401  (baselines import it from here)
from vprbench.weights import (  # noqa: F401  (baselines import these from here)
    ResolvedWeights,
    file_sha256,
    read_weights_file,
    resolve_weights,
    weights_provenance,
)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------- option parsing
def native_when_unset(options: dict) -> dict:
    """A method's `implied_options` where resize left unset is the image as stored: `resize=native`
    written out is the same run (one row, not two of the same numbers)."""
    return {"resize": "native"}


def as_int(value, name: str) -> int:
    """Options from `-o key=value` arrive as strings."""
    try:
        return int(value)
    except (TypeError, ValueError):
        raise VPRBenchError(f"Option {name} must be an integer, got {value!r}.") from None


def choose(kind: str, value: str, valid: Sequence[str], method: str) -> str:
    """Case-insensitive pick from `valid`, or an error that lists them."""
    by_lower = {v.lower(): v for v in valid}
    if str(value).lower() not in by_lower:
        raise VPRBenchError(f"{method}: unknown {kind} {value!r}; valid: {', '.join(valid)}.")
    return by_lower[str(value).lower()]


# ---------------------------------------------------------------- weights
def check_dim(method: str, dim, valid, what: str) -> int | None:
    """`dim` as an int if one of the released `valid` dimensions for `what`; None stays None."""
    if dim is None:
        return None
    dim = as_int(dim, "dim")
    if dim not in valid:
        raise VPRBenchError(f"{method}: dim {dim} is not available for {what}; valid: {', '.join(map(str, valid))}.")
    return dim


def weights_fields(resolved: ResolvedWeights, source: WeightSource) -> dict:
    """The fingerprint's weights fields: the user's file by its sha256, a release by its URL
    (and published sha256), a hub file by 'hf:<repo>/<file>'."""
    if resolved.identity.startswith("sha256:"):
        return {"weights_sha256": resolved.identity.removeprefix("sha256:")}
    if resolved.identity.startswith("hf:"):
        return {"weights": resolved.identity}
    return {"weights_url": resolved.identity, "weights_sha256": source.sha256}


def load_checkpoint(weights: str | os.PathLike | None, source: WeightSource, method: str, cache_dir=None):
    """The checkpoint object and the weights identity for the fingerprint, from the one
    resolver (`vprbench.weights.resolve_weights`): the user's `--weights PATH`, else the
    published file downloaded once into the cache."""
    resolved = resolve_weights(source, weights, method, cache_dir=cache_dir)
    return read_weights_file(resolved.path, "checkpoint"), weights_fields(resolved, source)


def state_dict_of(checkpoint, keys: Sequence[str] = ("state_dict", "model_state_dict")) -> dict:
    """The tensor dict inside a checkpoint (training checkpoints nest it), without DataParallel's 'module.'."""
    if isinstance(checkpoint, Mapping):
        for key in keys:
            if key in checkpoint and isinstance(checkpoint[key], Mapping):
                checkpoint = checkpoint[key]
                break
    if not isinstance(checkpoint, Mapping):
        raise VPRBenchError(f"Checkpoint holds a {type(checkpoint).__name__}, not a state dict.")
    # nn.DataParallel adds a "module." segment (whole model or one submodule) when training on several GPUs
    return {".".join(part for part in k.split(".") if part != "module"): v for k, v in checkpoint.items()}


def load_exact(model: nn.Module, state_dict: Mapping, method: str, limit: int = 8,
               hint: str = "Check that the weights belong to the chosen backbone and dimension.") -> None:
    """Load every parameter (taking the checkpoint's tensors), or name the missing, unexpected
    and mis-shaped keys, then `hint` (what to do)."""
    expected = model.state_dict()
    missing = [k for k in expected if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expected]
    wrong = [
        f"{k} {tuple(state_dict[k].shape)} (expected {tuple(v.shape)})"
        for k, v in expected.items()
        if k in state_dict and tuple(state_dict[k].shape) != tuple(v.shape)
    ]
    problems = []
    for label, keys in (("missing", missing), ("unexpected", unexpected), ("wrong shape", wrong)):
        if keys:
            shown = ", ".join(keys[:limit]) + (f" and {len(keys) - limit} more" if len(keys) > limit else "")
            problems.append(f"{label}: {shown}")
    if problems:
        raise VPRBenchError(f"{method}: the checkpoint does not match this architecture ({'; '.join(problems)}). {hint}")
    model.load_state_dict(state_dict, strict=True, assign=True)


def build_loaded(build, state_dict: Mapping, method: str) -> nn.Module:
    """`build()` on the meta device (no random init to throw away), then take the checkpoint's tensors."""
    with torch.device("meta"):
        model = build()
    load_exact(model, state_dict, method)
    return model.float()


# ---------------------------------------------------------------- preprocessing
#: `preprocess` of a baseline AnyLoc compares with: "authors" (its own code's) or "anyloc" (AnyLoc's
#: evaluation: its dataset loaders normalise first and resize the tensor without antialiasing, as
#: torchvision 0.14 did)
PREPROCESSING = ("authors", "anyloc")


def preprocess_for(mode: str, method: str, resize, interpolation: str = "bilinear") -> "Preprocess":
    """The Preprocess of `mode` (one of PREPROCESSING); AnyLoc's resize is bilinear on the tensor."""
    if choose("preprocess", mode, PREPROCESSING, method) == "anyloc":
        return Preprocess(resize=resize, normalise_first=True, antialias=False)
    return Preprocess(resize=resize, interpolation=interpolation)


@dataclass(frozen=True)
class Preprocess:
    """How the authors turn an image file into a network input.

    resize: (H, W) to resize to exactly, an int for the shorter side, or None for full resolution.
    normalise_first: False = resize the PIL image, then ToTensor + Normalize (torchvision
    transforms.Resize on images); True = normalise the full image and resize the tensor after,
    as some code bases do, with `antialias` as their torchvision version had it.
    """

    resize: tuple[int, int] | int | None = None
    interpolation: str = "bilinear"
    mean: tuple[float, float, float] = IMAGENET_MEAN
    std: tuple[float, float, float] = IMAGENET_STD
    normalise_first: bool = False
    antialias: bool = True

    def __call__(self, path: Path) -> torch.Tensor:
        from torchvision.transforms import InterpolationMode
        from torchvision.transforms import functional as F

        image = load_image(path, "RGB")
        mode = InterpolationMode(self.interpolation)
        size = list(self.resize) if isinstance(self.resize, tuple) else self.resize
        if self.normalise_first:
            tensor = F.normalize(F.to_tensor(image), self.mean, self.std)
            if size is not None:
                tensor = F.resize(tensor, size, interpolation=mode, antialias=self.antialias)
            return tensor
        if size is not None:
            image = F.resize(image, size, interpolation=mode)
        return F.normalize(F.to_tensor(image), self.mean, self.std)

    def fingerprint(self) -> dict:
        return {
            "resize": list(self.resize) if isinstance(self.resize, tuple) else self.resize,
            "interpolation": self.interpolation,
            "mean": list(self.mean),
            "std": list(self.std),
            "normalise_first": self.normalise_first,
            "antialias": self.antialias,
        }


# ---------------------------------------------------------------- the Method
_DTYPES = {"fp32": torch.float32, "fp16": torch.float16, "bf16": torch.bfloat16}


class TorchMethod(Method):
    """A torch model (image batch -> descriptors) plus its preprocessing.

    Images of different sizes (full-resolution evaluation) are run in groups of equal
    size; every network here is per-image in eval mode, so a row never depends on its batch.
    """

    def __init__(
        self,
        model: nn.Module,
        preprocess: Preprocess,
        fingerprint: dict,
        *,
        batch_size: int | None = None,
        device: str = "cpu",
        precision: str = "fp32",
        dim: int | None = None,
    ):
        if precision not in _DTYPES:
            raise VPRBenchError(f"Unknown precision {precision!r}; valid: {', '.join(_DTYPES)}.")
        try:
            self.device = torch.device(device)
        except RuntimeError:
            raise VPRBenchError(f"Unknown device {device!r}; use cpu or cuda.") from None
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise VPRBenchError("Device cuda was requested but no CUDA GPU is available; use --device cpu.")
        self.model = model.eval().to(self.device)
        self.preprocess = preprocess
        self.precision = precision
        self.dim = dim
        self._fingerprint = {**fingerprint, "preprocess": preprocess.fingerprint(), "precision": precision}
        if batch_size is not None:
            self.batch_size = as_int(batch_size, "batch_size")

    def fingerprint(self) -> dict:
        return dict(self._fingerprint)

    def load(self, path: Path) -> torch.Tensor:
        """Read and preprocess one image (in a data-loader worker)."""
        return self.preprocess(Path(path))

    def provenance(self) -> dict:
        """The weights' source, read from the identity `load_checkpoint` (or a baseline's own
        resolver) put in the fingerprint: a release URL, a hub file ('hf:<repo>/<file>'), or the
        sha256 of the user's file. Every layer (PCA and vocabulary included) comes from the checkpoint."""
        fp = self._fingerprint
        if fp.get("weights_url"):
            identity = fp["weights_url"]
        elif isinstance(fp.get("weights"), str):
            identity = fp["weights"]
        elif fp.get("weights_sha256"):
            identity = "sha256:" + fp["weights_sha256"]
        else:
            identity = None
        weights = weights_provenance(identity)
        if fp.get("hf_hub"):
            weights["hub"] = fp["hf_hub"]
        return {"weights": weights}

    @torch.inference_mode()
    def describe(self, images: Sequence) -> np.ndarray:
        tensors = loaded(self, images)
        out: list[np.ndarray | None] = [None] * len(tensors)
        groups: dict[tuple, list[int]] = {}
        for index, tensor in enumerate(tensors):
            groups.setdefault(tuple(tensor.shape), []).append(index)
        for indices in groups.values():
            for start in range(0, len(indices), max(1, self.batch_size)):
                chunk = indices[start : start + self.batch_size]
                batch = torch.stack([tensors[i] for i in chunk]).to(self.device)
                with torch.autocast(self.device.type, dtype=_DTYPES[self.precision], enabled=self.precision != "fp32"):
                    descriptors = self.model(batch)
                rows = descriptors.float().cpu().numpy()
                for i, row in zip(chunk, rows):
                    out[i] = row
        if not out:
            return np.zeros((0, self.dim or 0), dtype=np.float32)
        return l2_normalise(np.stack(out))
