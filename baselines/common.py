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
from vprbench.paths import cache_root
from vprbench.weights import file_sha256, read_torch_file, weights_provenance  # noqa: F401  (baselines import file_sha256 from here)

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


# ---------------------------------------------------------------- option parsing
def as_int(value, name: str) -> int:
    """Options from `-o key=value` arrive as strings."""
    try:
        return int(value)
    except (TypeError, ValueError):
        raise VPRBenchError(f"Option {name} must be an integer, got {value!r}.") from None


def as_resize(value, name: str = "resize") -> tuple[int, int] | None:
    """(H, W) from a tuple, "HxW", "H,W" or a single int for a square."""
    if value is None:
        return None
    if isinstance(value, str):
        parts = value.lower().replace("x", ",").split(",")
        value = tuple(p.strip() for p in parts if p.strip())
    if isinstance(value, int):
        value = (value, value)
    if len(value) == 1:
        value = (value[0], value[0])
    if len(value) != 2:
        raise VPRBenchError(f"Option {name} takes height and width (e.g. 480 640), got {value!r}.")
    height, width = (as_int(v, name) for v in value)
    if height <= 0 or width <= 0:
        raise VPRBenchError(f"Option {name} must be positive, got {height}x{width}.")
    return height, width


def choose(kind: str, value: str, valid: Sequence[str], method: str) -> str:
    """Case-insensitive pick from `valid`, or an error that lists them."""
    by_lower = {v.lower(): v for v in valid}
    if str(value).lower() not in by_lower:
        raise VPRBenchError(f"{method}: unknown {kind} {value!r}; valid: {', '.join(valid)}.")
    return by_lower[str(value).lower()]


# ---------------------------------------------------------------- weights
@dataclass(frozen=True)
class WeightSource:
    """Where the authors publish a checkpoint.

    `url` is a direct download (None when it is only on a page that needs a browser,
    such as Google Drive); `page` is where a person gets it; `sha256` only when the
    authors publish one.
    """

    file_name: str
    url: str | None = None
    page: str | None = None
    sha256: str | None = None

    def how_to_get(self) -> str:
        where = self.url or self.page or "the authors' release page"
        return f"download {self.file_name} from {where} and pass it with --weights PATH"


def weights_dir() -> Path:
    """torch hub checkpoint folder: $TORCH_HOME when set, else under the vprbench cache."""
    if os.environ.get("TORCH_HOME"):
        return Path(torch.hub.get_dir()) / "checkpoints"
    return cache_root() / "torch" / "hub" / "checkpoints"


def check_dim(method: str, dim, valid, what: str) -> int | None:
    """`dim` as an int if one of the released `valid` dimensions for `what`; None stays None."""
    if dim is None:
        return None
    dim = as_int(dim, "dim")
    if dim not in valid:
        raise VPRBenchError(f"{method}: dim {dim} is not available for {what}; valid: {', '.join(map(str, valid))}.")
    return dim


def load_checkpoint(weights: str | os.PathLike | None, source: WeightSource, method: str):
    """The checkpoint object and the weights identity for the fingerprint.

    `weights` is a local file (the user's `--weights PATH`); without it the published
    URL is downloaded once into the torch hub cache (hash-checked when a sha256 is
    published). Offline, or when there is no direct URL, the error says how to supply it.
    """
    if weights is not None:
        path = Path(weights).expanduser()
        if not path.is_file():
            raise VPRBenchError(f"{method}: weights file {path} does not exist; {source.how_to_get()}.")
        return read_torch_file(path), {"weights_sha256": file_sha256(path)}
    if source.url is None:
        raise VPRBenchError(
            f"{method}: the authors publish {source.file_name} only at {source.page}, which cannot be "
            f"downloaded automatically; download it there and pass it with --weights PATH."
        )
    identity = {"weights_url": source.url, "weights_sha256": source.sha256}
    target = weights_dir() / source.file_name
    if not target.is_file():
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            torch.hub.download_url_to_file(source.url, str(target), hash_prefix=source.sha256, progress=False)
        except (OSError, RuntimeError) as error:  # URLError is an OSError; RuntimeError = hash mismatch
            raise VPRBenchError(
                f"{method}: could not download {source.file_name} from {source.url} ({error}). "
                f"Offline? {source.how_to_get()}."
            ) from None
    return read_torch_file(target), identity


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


def load_exact(model: nn.Module, state_dict: Mapping, method: str, limit: int = 8) -> None:
    """Load every parameter (taking the checkpoint's tensors), or name the missing, unexpected
    and mis-shaped keys."""
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
        raise VPRBenchError(
            f"{method}: the checkpoint does not match this architecture ({'; '.join(problems)}). "
            "Check that the weights belong to the chosen backbone and dimension."
        )
    model.load_state_dict(state_dict, strict=True, assign=True)


def build_loaded(build, state_dict: Mapping, method: str) -> nn.Module:
    """`build()` on the meta device (no random init to throw away), then take the checkpoint's tensors."""
    with torch.device("meta"):
        model = build()
    load_exact(model, state_dict, method)
    return model.float()


# ---------------------------------------------------------------- preprocessing
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
        resolver) put in the fingerprint: a release URL, a release name ('open_clip:...'), or the
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
