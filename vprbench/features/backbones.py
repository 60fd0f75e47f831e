"""ViT backbones built with timm from their manifest entries (features/catalogue.py).

Weights come from a local file (`weights=PATH`: the authors' release format or timm's; a JAX
`.npz` release such as SigLIP 2's is read by timm's own loader), from the entry's weight source
through the one resolver (vprbench.weights), or, with `weights="random"`, from a seeded random
initialisation (a pipeline check; recorded as random).
"""
from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Iterator
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


@contextlib.contextmanager
def own_defaults(seed: int | None = None) -> Iterator[None]:
    """Modules built inside get float32 CPU tensors and (with `seed`) a seeded initialisation whatever the
    caller set (torch.set_default_dtype/device, their own seed): else `weights="random"` gave other weights,
    under the same fingerprint, in a notebook that had set float64. The caller's random stream and
    defaults are left as they were."""
    dtype = torch.get_default_dtype()
    with torch.random.fork_rng(devices=[]), torch.device("cpu"):
        torch.set_default_dtype(torch.float32)
        try:
            if seed is not None:
                torch.default_generator.manual_seed(seed)  # the CPU's only: initialisation runs there
            yield
        finally:
            torch.set_default_dtype(dtype)


def create_model(spec: BackboneEntry, *, empty: bool = False, seed: int | None = None, **overrides) -> nn.Module:
    """The timm architecture without a classifier head: random weights (seeded with `seed`), or,
    with `empty`, parameters without storage (on the meta device) to be filled by a state dict.
    `overrides` are timm keyword arguments (tests build tiny models: depth=2, embed_dim=...)."""
    import timm

    if not timm.is_model(spec.timm):  # an older timm than the entry needs (timm adds architectures release by release)
        raise VPRBenchError(f"Backbone {spec.name} is timm's architecture {spec.timm!r}, which the timm installed here "
                            f"({timm.__version__}) does not have: upgrade timm (pip install -U timm).")
    kwargs = {"pretrained": False, "num_classes": 0, **spec.timm_kwargs, **overrides}
    with own_defaults(), torch.device("meta"):  # skips the random initialisation of large models
        shape = timm.create_model(spec.timm, **kwargs).eval()
    _check_memory(spec, shape)
    if empty:
        return shape
    with own_defaults(seed):
        return _as_released(timm.create_model(spec.timm, **kwargs).eval(), spec)


def _check_memory(spec: BackboneEntry, model: nn.Module) -> None:
    """A model whose float32 weights exceed this machine's memory is refused from its shapes alone,
    before it is built or a file read: built, it (a 7B ViT: 28 GB) got the process killed without a word."""
    from ..evaluation import provenance  # the module, so the machine's memory can be stood in for

    needed = 4 * sum(t.numel() for t in (*model.parameters(), *model.buffers()))
    memory = provenance.memory_bytes()
    if memory is not None and needed > memory:
        raise VPRBenchError(f"Backbone {spec.name} needs {needed / 2**30:.1f} GiB for its float32 weights alone, more "
                            f"than this machine's {memory / 2**30:.1f} GiB of memory: choose a smaller backbone, or run "
                            "on a machine with more memory.")


def _as_released(model: nn.Module, spec: BackboneEntry) -> nn.Module:
    """RoPE periods in the release's precision: DINOv3 keeps them as a bfloat16 buffer where timm
    computes float32; truncated, the outputs match the release's (timm's model card says so)."""
    if spec.rope_periods == "bfloat16":
        with torch.no_grad():
            model.rope.periods.copy_(model.rope.periods.to(torch.bfloat16).float())
    return model


def _materialise(model: nn.Module, spec: BackboneEntry) -> nn.Module:
    """A model built on the meta device and given its state dict still lacks the buffers no
    checkpoint holds (RoPE periods and tables): timm computes them."""
    from timm.models._manipulate import reinit_non_persistent_buffers

    for module in model.modules():
        for name, buffer in list(module.named_buffers(recurse=False)):
            if buffer.is_meta:  # only non-persistent buffers are left out of a strict load
                module.register_buffer(name, torch.empty_like(buffer, device="cpu"), persistent=False)
    reinit_non_persistent_buffers(model)
    return _as_released(model, spec)


def weights_identity(spec: BackboneEntry, weights: str | Path | None, cache_dir=None) -> str | None:
    """'sha256:<hex>' of a local file (or of a file in `cache_dir` vprbench did not download), the
    release URL / 'hf:<repo>/<file>', None for random weights (nothing is downloaded)."""
    if weights == RANDOM:
        return None
    return resolver_identity(spec.source, weights, f"backbone {spec.name}", cache_dir)


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


def _misfit(missing=(), unexpected=(), mismatched=()) -> VPRBenchError:
    return VPRBenchError(
        "The weights file does not fit this backbone (wrong architecture?). "
        f"Missing keys: {_show(sorted(missing))}. Unexpected keys: {_show(sorted(unexpected))}. "
        f"Shape mismatches: {_show(list(mismatched))}. Pass a checkpoint of this backbone, or choose the backbone "
        "the file was saved from."
    )


def _grid_mismatches(state: dict, expected: dict) -> list[str]:
    """A position embedding or patch kernel of another size: timm's filter would resample it
    silently, but such a file is another architecture. Position embeddings are compared by their
    grid (a release may hold one slot more for the CLS token, as DINOv2 with registers)."""
    found = []
    for key in ("pos_embed", "patch_embed.proj.weight"):
        if key not in state or key not in expected:
            continue
        file, model = tuple(state[key].shape), tuple(expected[key].shape)
        same = (len(file) >= 2 and file[-1] == model[-1] and math.isqrt(file[-2]) == math.isqrt(model[-2])) \
            if key == "pos_embed" else file == model
        if not same:
            found.append(f"{key}: file {file} vs model {model}")
    return found


def _check_values(state: dict, expected: dict) -> None:
    """Every value a tensor, of floating point where the model's is (timm's filter and torch's loader
    would fail on them with their own tracebacks)."""
    found = [f"{key} ({type(value).__name__})" for key, value in state.items() if not isinstance(value, torch.Tensor)]
    found += [f"{key} ({str(value.dtype).removeprefix('torch.')})" for key, value in state.items()
              if isinstance(value, torch.Tensor) and key in expected and not value.is_floating_point()
              and expected[key].is_floating_point()]
    if found:
        raise VPRBenchError(f"The weights file holds values that are no floating-point tensors: {_show(found)}. "
                            "Pass the checkpoint's weights as saved by PyTorch (a state dict of float tensors).")


def _drop_unplaced_biases(state: dict, expected: dict) -> dict:
    """Fused q/k/v biases the file holds but the architecture has no place for (DINOv3's release
    keeps all-zero, masked ones: `qkv.bias` times `qkv.bias_mask`): dropped when they add
    nothing, refused otherwise."""
    state = dict(state)
    for key in [k for k in state if k.endswith("attn.qkv.bias")]:
        named_as_the_model = key.replace("qkv.bias", "qkv.weight") in expected
        if not named_as_the_model or key in expected or key.replace("qkv.bias", "q_bias") in expected:
            continue
        bias, mask = state.pop(key), state.pop(key + "_mask", None)
        if (bias if mask is None else bias * mask).any():
            raise VPRBenchError(f"The weights file has non-zero attention biases ({key}) that this architecture has "
                                "none of; choose the timm architecture with q/k/v biases (backbone=timm:ARCH.TAG, "
                                "e.g. the *_qkvb DINOv3 variants).")
    return state


def convert_official(state: dict[str, torch.Tensor], model: nn.Module) -> dict[str, torch.Tensor]:
    """Official (or timm) checkpoint keys -> the model's, by the timm module's own checkpoint
    filter (DINOv2 SwiGLU w12/w3 -> fc1/fc2, DINOv2 register_tokens, DINOv3 storage_tokens and
    ls1.gamma, Perception Encoder and C-RADIO releases, ...), refusing what does not fit: a
    position embedding or patch kernel of another size (which the filter would resample), missing,
    unexpected or misshapen keys."""
    filter_fn = getattr(sys.modules[type(model).__module__], "checkpoint_filter_fn", None)
    expected = model.state_dict()
    _check_values(state, expected)
    mismatched = _grid_mismatches(state, expected)
    state = _drop_unplaced_biases(state, expected)
    try:
        converted = filter_fn(dict(state), model) if filter_fn is not None and not mismatched else state
    except RuntimeError:  # the filter cannot place a tensor (a position table with another count of prefix slots)
        converted = state  # compared as they are below (the filter changed a copy), naming the keys at fault
    # a classifier or projection head beside the trunk (timm's head.*, e.g. Perception Encoder core's
    # proj): these models are built without one, and AnyLoc reads the trunk
    converted = {k: v for k, v in converted.items() if k in expected or not k.startswith("head.")}
    mismatched += [f"{k}: file {tuple(v.shape)} vs model {tuple(expected[k].shape)}" for k, v in converted.items()
                   if k in expected and v.shape != expected[k].shape and not any(m.startswith(k + ":") for m in mismatched)]
    missing, unexpected = set(expected) - set(converted), set(converted) - set(expected)
    if missing or unexpected or mismatched:
        raise _misfit(missing, unexpected, mismatched)
    return converted


#: where timm's loader of JAX .npz checkpoints looks for the image tower (big_vision two-tower files: params/img/)
NPZ_PREFIXES = ("params/img/", "params/", "opt/target/", "")


def read_npz_release(spec: BackboneEntry, path: Path) -> nn.Module:
    """A JAX/Flax `.npz` release (Google's big_vision format, e.g. SigLIP 2's two-tower file) read
    by timm's own loader into the architecture. Every parameter starts as NaN, so one the file does
    not fill is named; a patch kernel or position grid of another size is refused (timm would
    resample it)."""
    from ..datasets.layouts.npy import npz_headers

    model = create_model(spec)
    if not hasattr(model, "load_pretrained"):
        raise VPRBenchError(f"{path}: .npz files are read for timm VisionTransformer architectures only; backbone "
                            f"{spec.name} ({spec.timm}) takes a PyTorch or .safetensors file.")
    try:
        # every member checked before timm's loader reads them all: a header claiming terabytes, or
        # Python objects, is refused here unread. Nothing is unpacked here, and a two-tower release
        # holds a text tower timm never reads (unbounded together): what timm reads is bounded below
        shapes = {name: shape for name, (shape, _) in npz_headers(
            path, "weights file", "a complete .npz archive of numeric arrays: pass the release file as published "
            "(download it again), or another", kinds="iuf", max_bytes=sys.maxsize).items()}
    except OSError as error:
        raise VPRBenchError(f"Cannot read weights file {path}: {error}.") from None
    prefix = next((p for p in NPZ_PREFIXES if p + "embedding/kernel" in shapes), None)
    if prefix is None:
        raise _misfit(missing=["embedding/kernel (the patch embedding of a ViT image tower)"])
    # timm reads each array it loads whole before it compares it with a parameter: one holding more
    # values than any parameter (a deflated bomb of zeros) fits none. A classifier it has no layer
    # for (vprbench's models have none) it never reads: an in21k release's (D, 21843) head is harmless
    classifiers = {"head/": model.head, "pre_logits/": getattr(getattr(model, "pre_logits", None), "fc", None)}
    unread = tuple(prefix + part for part, layer in classifiers.items() if not isinstance(layer, nn.Linear))
    largest = max(parameter.numel() for parameter in model.parameters())
    oversized = [f"{name}: file {shape} holds more values than any parameter of the model ({largest:,})"
                 for name, shape in shapes.items()
                 if name.startswith(prefix) and not name.startswith(unread) and math.prod(shape) > largest]
    if oversized:
        raise _misfit(mismatched=oversized)
    kernel = shapes[prefix + "embedding/kernel"]
    grid = next((shapes[prefix + k] for k in ("pos_embedding", "Transformer/posembed_input/pos_embedding")
                 if prefix + k in shapes), None)
    expected = model.state_dict()
    # shapes only (meta tensors hold no storage): a file's shapes may multiply to anything
    found = {"patch_embed.proj.weight": torch.empty(kernel[::-1][:2] + kernel[:2], device="meta")}
    if grid is not None:
        found["pos_embed"] = torch.empty(grid, device="meta")
    mismatched = _grid_mismatches(found, expected)
    if mismatched:
        raise _misfit(mismatched=mismatched)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.fill_(float("nan"))
        try:
            model.load_pretrained(str(path))
        except KeyError as error:
            raise _misfit(missing=[str(error).strip("'\"")]) from None
        except (RuntimeError, ValueError) as error:
            raise _misfit(mismatched=[str(error).splitlines()[0]]) from None
    unfilled = [name for name, parameter in model.named_parameters() if parameter.isnan().any()]
    if unfilled:
        raise _misfit(missing=unfilled)
    return _as_released(model, spec)


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
            _LOADED.clear()
            _LOADED[key] = (create_model(spec, seed=RANDOM_SEED).float().to(device), None)
        model, identity = _LOADED[key]
        return model, spec, identity
    resolved = resolve_weights(spec.source, weights, f"backbone {spec.name}", cache_dir=cache_dir)
    path, identity = resolved.path, resolved.identity
    stat = path.stat()
    key = (name, str(path.resolve()), stat.st_mtime_ns, stat.st_size, str(device))
    if key not in _LOADED:
        try:
            model = read_npz_release(spec, path) if path.suffix == ".npz" else _load_state(spec, path)
        except VPRBenchError as error:  # the file named once
            said = str(error)
            raise VPRBenchError(f"Backbone {spec.name}: {said}" if str(path) in said else
                                f"{path} for backbone {spec.name}: {said}") from None
        _LOADED.clear()  # keep one model: a ViT-G takes 4.5 GB
        _LOADED[key] = (model.float().eval().to(device), identity)
    model, identity = _LOADED[key]
    return model, spec, identity


def _load_state(spec: BackboneEntry, path: Path) -> nn.Module:
    model = create_model(spec, empty=True)
    model.load_state_dict(convert_official(read_checkpoint(path), model), strict=True, assign=True)
    with own_defaults():  # the buffers no checkpoint holds (RoPE tables) computed as timm does
        return _materialise(model, spec)
