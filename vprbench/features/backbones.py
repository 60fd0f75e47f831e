"""Self-supervised ViT backbones (DINOv2, DINO v1) built with timm from official checkpoints.

A backbone is a small record (timm architecture, patch size, official weight file and URL).
Weights come from a local file in the official checkpoint format (`weights=PATH`) or are
downloaded once from the official release URL into the torch hub cache.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ..errors import VPRBenchError, closest_names
from ..weights import WeightSource, read_weights_file, resolve_weights
from ..weights import weights_identity as resolver_identity


@dataclass(frozen=True)
class BackboneSpec:
    name: str
    timm_arch: str
    family: str  # "dinov2" or "dino"
    patch: int
    url: str
    depth: int  # number of blocks
    dim: int  # feature dimension of every block and facet (embedding width)

    @property
    def file_name(self) -> str:
        return self.url.rsplit("/", 1)[-1]

    @property
    def source(self) -> WeightSource:
        return WeightSource(self.file_name, url=self.url)


_DINOV2 = "https://dl.fbaipublicfiles.com/dinov2/{0}/{0}_pretrain.pth"
_DINO = "https://dl.fbaipublicfiles.com/dino/{0}/{0}.pth"

BACKBONES: dict[str, BackboneSpec] = {
    s.name: s
    for s in [
        BackboneSpec("dinov2_vits14", "vit_small_patch14_dinov2", "dinov2", 14, _DINOV2.format("dinov2_vits14"), 12, 384),
        BackboneSpec("dinov2_vitb14", "vit_base_patch14_dinov2", "dinov2", 14, _DINOV2.format("dinov2_vitb14"), 12, 768),
        BackboneSpec("dinov2_vitl14", "vit_large_patch14_dinov2", "dinov2", 14, _DINOV2.format("dinov2_vitl14"), 24, 1024),
        BackboneSpec("dinov2_vitg14", "vit_giant_patch14_dinov2", "dinov2", 14, _DINOV2.format("dinov2_vitg14"), 40, 1536),
        BackboneSpec("dino_vits8", "vit_small_patch8_224", "dino", 8, _DINO.format("dino_deitsmall8_pretrain"), 12, 384),
        BackboneSpec("dino_vits16", "vit_small_patch16_224", "dino", 16, _DINO.format("dino_deitsmall16_pretrain"), 12, 384),
        BackboneSpec("dino_vitb8", "vit_base_patch8_224", "dino", 8, _DINO.format("dino_vitbase8_pretrain"), 12, 768),
        BackboneSpec("dino_vitb16", "vit_base_patch16_224", "dino", 16, _DINO.format("dino_vitbase16_pretrain"), 12, 768),
    ]
}


def backbone_spec(name: str) -> BackboneSpec:
    if name not in BACKBONES:
        raise VPRBenchError(
            f"Unknown backbone {name!r}.{closest_names(name, BACKBONES)} "
            f"Available: {', '.join(BACKBONES)}."
        )
    return BACKBONES[name]


def create_model(spec: BackboneSpec, *, empty: bool = False) -> nn.Module:
    """The timm architecture with no classifier head: random weights, or, with `empty`,
    parameters without storage (on the meta device) to be filled by a state dict."""
    import timm

    if empty:
        with torch.device("meta"):  # skips the random initialisation of large models
            return timm.create_model(spec.timm_arch, pretrained=False, num_classes=0).eval()
    return timm.create_model(spec.timm_arch, pretrained=False, num_classes=0).eval()


# ---------------------------------------------------------------- weight files
def weights_identity(spec: BackboneSpec, weights: str | Path | None) -> str:
    """'sha256:<hex>' of a local file, else the official URL (nothing is downloaded)."""
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


def convert_official(state: dict[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """Official DINOv2/DINO checkpoint keys -> timm keys, refusing shape changes.

    timm's checkpoint filter renames DINOv2 keys (SwiGLU w12/w3 -> fc1/fc2, drops mask_token);
    it would also silently resample a position embedding or patch kernel of another size,
    so those shapes are checked first: such a file is another architecture.
    """
    from timm.models.vision_transformer import checkpoint_filter_fn

    expected = model.state_dict()
    mismatched = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(expected[k].shape)}"
        for k in ("pos_embed", "patch_embed.proj.weight")
        if k in state and k in expected and state[k].shape != expected[k].shape
    ]
    converted = checkpoint_filter_fn(dict(state), model) if not mismatched else dict(state)
    mismatched += [
        f"{k}: file {tuple(v.shape)} vs model {tuple(expected[k].shape)}"
        for k, v in converted.items()
        if k in expected and v.shape != expected[k].shape and k not in ("pos_embed", "patch_embed.proj.weight")
    ]
    missing = sorted(set(expected) - set(converted))
    unexpected = sorted(set(converted) - set(expected))
    if missing or unexpected or mismatched:
        def show(keys):
            return ", ".join(keys[:8]) + (f" (+{len(keys) - 8} more)" if len(keys) > 8 else "") if keys else "none"

        raise VPRBenchError(
            "The weights file does not fit this backbone (wrong architecture?). "
            f"Missing keys: {show(missing)}. Unexpected keys: {show(unexpected)}. "
            f"Shape mismatches: {show(mismatched)}."
        )
    return converted


#: loaded models, shared by methods in one process (they never modify a model)
_LOADED: dict[tuple, tuple[nn.Module, str]] = {}


def load_backbone(name: str, weights: str | Path | None = None, device: str | torch.device = "cpu",
                  cache_dir=None) -> tuple[nn.Module, BackboneSpec, str]:
    """(timm model in eval mode with official weights on `device`, spec, weights identity);
    the release is downloaded once into `cache_dir` unless `weights` names a local file."""
    spec = backbone_spec(name)
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


def official_state_dict(model: nn.Module, spec: BackboneSpec) -> dict[str, torch.Tensor]:
    """The timm model's weights under the official checkpoint's key names (inverse of
    `convert_official`; used to write official-format files, e.g. for tests)."""
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    if spec.family == "dinov2":
        renamed = {}
        for k, v in state.items():
            if ".mlp.fc1." in k and spec.name == "dinov2_vitg14":
                k = k.replace(".mlp.fc1.", ".mlp.w12.")
            elif ".mlp.fc2." in k and spec.name == "dinov2_vitg14":
                k = k.replace(".mlp.fc2.", ".mlp.w3.")
            renamed[k] = v
        state = renamed
        state["mask_token"] = torch.zeros(1, state["cls_token"].shape[-1])
    return state
