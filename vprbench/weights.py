"""Weight files, for every method that loads them: read safely, named by their content."""
from __future__ import annotations

import pickle
import struct
import tomllib
from functools import cache
from importlib.resources import files
from pathlib import Path

import numpy as np

from . import fsutil
from .errors import VPRBenchError

_SHA256: dict[tuple, str] = {}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes; remembered per (path, mtime, size), so multi-GB files hash once."""
    path = Path(path)
    stat = path.stat()
    key = (str(path.resolve()), stat.st_mtime_ns, stat.st_size)
    if key not in _SHA256:
        _SHA256[key] = fsutil.file_sha256(path)
    return _SHA256[key]


def _numpy_globals() -> list:
    """numpy scalars/arrays that training checkpoints pickle beside the tensors (scores, recalls),
    under their numpy 1.x and 2.x module names."""
    try:
        from numpy._core import multiarray
    except ImportError:  # numpy 1.x
        from numpy.core import multiarray
    allowed = [np.dtype, np.ndarray]
    allowed += [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType")]
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed += [(multiarray.scalar, f"{module}.scalar"), (multiarray._reconstruct, f"{module}._reconstruct")]
    return allowed


def read_torch_file(path: str | Path, what: str = "checkpoint", *, mmap: bool = False):
    """torch.load of tensors, containers and numpy scalars only: loading never runs code.

    `mmap` maps large zip-format files instead of copying them (legacy files are read whole).
    Any failure is a VPRBenchError naming the file.
    """
    import torch

    path = Path(path)
    try:
        with torch.serialization.safe_globals(_numpy_globals()):
            try:
                return torch.load(path, map_location="cpu", weights_only=True, mmap=mmap)
            except RuntimeError:
                if not mmap:
                    raise
                return torch.load(path, map_location="cpu", weights_only=True)  # legacy format cannot be mapped
    except pickle.UnpicklingError:
        try:
            extra = ", ".join(torch.serialization.get_unsafe_globals_in_checkpoint(path))
        except (RuntimeError, ValueError, OSError):  # only zip-format files can be inspected
            extra = ""
        if not extra:
            raise VPRBenchError(f"Cannot read {what} {path}: it is damaged or not a PyTorch file.") from None
        raise VPRBenchError(
            f"{what.capitalize()} {path} also holds Python objects ({extra}), which are not loaded because "
            "unpickling them can run code. If you trust the file, save its weights alone, e.g. "
            "torch.save(torch.load(FILE, weights_only=False)['state_dict'], 'weights.pth'), and pass that."
        ) from None
    except (RuntimeError, EOFError, OSError, KeyError, ValueError, IndexError, struct.error) as error:
        # what torch's unpickler raises on truncated or foreign files
        raise VPRBenchError(
            f"Cannot read {what} {path}: it is damaged or not a PyTorch file ({type(error).__name__}: {error})."
        ) from None


@cache
def official_releases() -> tuple[dict, ...]:
    """The official weight releases vprbench knows (manifests/weights.toml)."""
    text = (files("vprbench.manifests") / "weights.toml").read_text()
    return tuple(tomllib.loads(text)["release"])


def weights_provenance(identity: str | None) -> dict:
    """Where a method's weights came from, for result records and the leaderboard.

    `identity` is what fingerprints hold: the official URL (or 'open_clip:<arch>/<tag>') of a
    file vprbench downloaded from the authors' release, 'sha256:<hex>' for a local file, None
    for a model run without weights (random initialisation). A local file is official only when
    its sha256 equals one the authors publish (manifests/weights.toml); otherwise it is the
    user's file, identified by its sha256.
    """
    if identity is None:
        return {"source": "random"}
    if not identity.startswith("sha256:"):
        release = next((r for r in official_releases() if identity.startswith(r["url_prefix"])), None)
        return {"source": "official", "url": identity, "recognised_by": "download",
                **({"release": release["name"]} if release else {})}
    digest = identity.removeprefix("sha256:")
    for release in official_releases():
        for name, published in release.get("sha256", {}).items():
            if published.lower() == digest.lower():
                return {"source": "official", "sha256": digest, "recognised_by": "sha256",
                        "release": release["name"], "file": name, "checksum_source": release.get("checksum_source", "")}
    return {"source": "user", "sha256": digest}
