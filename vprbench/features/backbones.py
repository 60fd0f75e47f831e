"""ViT backbones built with timm from their manifest entries (features/catalogue.py).

Weights come from a local file (`weights=PATH`, the official release format or timm's), from
the entry's weight source through the one resolver (vprbench.weights), or, with
`weights="random"`, from a seeded random initialisation (a pipeline check; recorded as random).
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch import nn

from ..errors import VPRBenchError
from ..weights import read_weights_file, resolve_weights
from ..weights import weights_identity as resolver_identity
from .catalogue import BackboneEntry, backbone_spec

#: `weights=` value for a seeded random initialisation
RANDOM = "random"
RANDOM_SEED = 0


def create_model(spec: BackboneEntry, *, empty: bool = False, **overrides) -> nn.Module:
    """The timm architecture without a classifier head: random weights, or, with `empty`,
    parameters without storage (on the meta device) to be filled by a state dict.
    `overrides` are timm keyword arguments (tests build tiny models: depth=2, embed_dim=...)."""
    import timm

    kwargs = {"pretrained": False, "num_classes": 0, **overrides}
    if spec.position_interpolation == "timm":
        kwargs.setdefault("dynamic_img_size", True)  # timm resamples its position embedding to any grid
    if empty:
        with torch.device("meta"):  # skips the random initialisation of large models
            return timm.create_model(spec.timm, **kwargs).eval()
    return timm.create_model(spec.timm, **kwargs).eval()


def weights_identity(spec: BackboneEntry, weights: str | Path | None) -> str | None:
    """'sha256:<hex>' of a local file, the release URL / 'hf:<repo>/<file>', None for random weights
    (nothing is downloaded)."""
    if weights == RANDOM:
        return None
    return resolver_identity(spec.source, weights, f"backbone {spec.name}")


def read_checkpoint(path: Path) -> dict[str, torch.Tensor]:
    state = read_weights_file(path, "weights file")
    # DINO v1 training checkpoints wrap the weights; the released *_pretrain.pth are flat
    for key in ("teacher", "model", "state_dict"):
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
    if not isinstance(state, dict):
        raise VPRBenchError(f"Weights file {path} does not hold a state dict (got {type(state).__name__})")
    return {k.removeprefix("module.").removeprefix("backbone."): v for k, v in state.items()}


def _show(keys: list[str]) -> str:
    return ", ".join(keys[:8]) + (f" (+{len(keys) - 8} more)" if len(keys) > 8 else "") if keys else "none"


def convert_official(state: dict[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """Official (or timm) checkpoint keys -> the model's, by the timm module's own checkpoint
    filter (DINOv2 SwiGLU w12/w3 -> fc1/fc2, DINOv3 storage_tokens -> reg_token, ...), refusing
    shape changes: timm's filter would silently resample a position embedding or patch kernel
    of another size, so those are checked first (such a file is another architecture)."""
    filter_fn = getattr(sys.modules[type(model).__module__], "checkpoint_filter_fn", None)
    expected = model.state_dict()
    mismatched = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in ("pos_embed", "patch_embed.proj.weight")
        if k in state and k in expected and state[k].shape != expected[k].shape
    ]
    converted = filter_fn(dict(state), model) if filter_fn is not None and not mismatched else dict(state)
    mismatched += [
        f"{k}: file {tuple(v.shape)} vs model {tuple(expected[k].shape)}"
        for k, v in converted.items()
        if k in expected and v.shape != expected[k].shape and k not in ("pos_embed", "patch_embed.proj.weight")
    ]
    missing = sorted(set(expected) - set(converted))
    unexpected = sorted(set(converted) - set(expected))
    if missing or unexpected or mismatched:
        raise VPRBenchError(
            "The weights file does not fit this backbone (wrong architecture?). "
            f"Missing keys: {_show(missing)}. Unexpected keys: {_show(unexpected)}. "
            f"Shape mismatches: {_show(mismatched)}."
        )
    return converted


#: loaded models, shared by methods in one process (they never modify a model)
_LOADED: dict[tuple, tuple[nn.Module, str | None]] = {}


def load_backbone(name: str, weights: str | Path | None = None, device: str | torch.device = "cpu",
                  cache_dir=None) -> tuple[nn.Module, BackboneEntry, str | None]:
    """(timm model in eval mode on `device`, its manifest entry, weights identity).

    The release is downloaded once into `cache_dir` unless `weights` names a local file;
    `weights="random"` is a seeded random initialisation (identity None)."""
    spec = backbone_spec(name)
    if weights == RANDOM:
        key = (name, RANDOM, str(device))
        if key not in _LOADED:
            torch.manual_seed(RANDOM_SEED)
            _LOADED.clear()
            _LOADED[key] = (create_model(spec).float().to(device), None)
        model, identity = _LOADED[key]
        return model, spec, identity
    resolved = resolve_weights(spec.source, weights, f"backbone {spec.name}", cache_dir=cache_dir)
    path, identity = resolved.path, resolved.identity
    stat = path.stat()
    key = (name, str(path.resolve()), stat.st_mtime_ns, stat.st_size, str(device))
    if key not in _LOADED:
        model = create_model(spec, empty=True)
        state = read_checkpoint(path)
        try:
            model.load_state_dict(convert_official(state, model), strict=True, assign=True)
        except VPRBenchError as error:
            raise VPRBenchError(f"{path} for backbone {spec.name}: {error}") from None
        _LOADED.clear()  # keep one model: a ViT-G takes 4.5 GB
        _LOADED[key] = (model.float().eval().to(device), identity)
    model, identity = _LOADED[key]
    return model, spec, identity


def official_state_dict(model: nn.Module, spec: BackboneEntry) -> dict[str, torch.Tensor]:
    """The timm model's weights under the release's key names (the entry's `official_rename`
    and `official_extra`; the inverse of `convert_official`, used to write official-format
    files, e.g. for tests)."""
    state = {}
    for key, value in model.state_dict().items():
        for timm_part, official_part in spec.official_rename.items():
            key = key.replace(timm_part, official_part)
        state[key] = value.detach().clone()
    for extra in spec.official_extra:  # present in the release, unused by inference
        state[extra] = torch.zeros(1, model.embed_dim) if extra == "mask_token" else torch.zeros(1)
    return state
