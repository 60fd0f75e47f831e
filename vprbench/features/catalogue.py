"""Backbones as data: manifests/backbones/*.toml, validated (pydantic) into `BackboneEntry`.

An entry says everything the dense extractor, the preprocessing, the weights resolver and
the records need (timm architecture and weights tag, patch, prefix tokens, position kind,
mean/std, resize rule, depth and width, facets, weight sources, licence, gating), so no code
branches on a family name. Any other timm ViT is reachable as `timm:ARCH.TAG` (read from
timm's own pretrained config when it is asked for). No torch here: listing backbones is cheap.
"""
from __future__ import annotations

import inspect
import re
import tomllib
from functools import cache
from importlib.resources import files
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..errors import VPRBenchError, closest_names
from ..weight_source import WeightSource

TIMM_PREFIX = "timm:"
#: a timm model name: an architecture (letters, digits, '_'), then optionally '.' and a weights tag
TIMM_NAME = re.compile(r"[A-Za-z0-9_]+(\.[A-Za-z0-9_-]+)?")
IMAGENET = ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))
#: timm keywords that load weights or replace the head: the one resolver loads weights, and
#: `--weights random` must stay random (timm would download the pretrained file itself)
TIMM_RESERVED = {"pretrained", "pretrained_cfg", "pretrained_cfg_overlay", "pretrained_strict", "checkpoint_path",
                 "cache_dir", "num_classes", "features_only"}
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
#: counts and flags as TOML writes them (strict: `patch = true` or `gated = "no"` is no value of theirs)
Count = Annotated[int, Field(strict=True, gt=0)]
Flag = Annotated[bool, Field(strict=True)]


class BackboneEntry(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(pattern=r"^[A-Za-z0-9_.:-]+$")
    family: str
    timm: str = Field(pattern=r"^[A-Za-z0-9_]+$")  # timm architecture
    tag: str = Field("", pattern=r"^[A-Za-z0-9_-]*$")  # timm weights tag (the pretrained config)
    patch: Count
    cls_token: Flag
    registers: int = Field(strict=True, ge=0)
    position: Literal["learned", "rope"]
    #: "dino": the official DINO/DINOv2 bicubic resampling of learned embeddings ((grid + 0.1) / M);
    #: "timm": the model's own (timm's `_pos_embed`, run through `forward_intermediates`)
    position_interpolation: Literal["dino", "timm"]
    depth: Count
    width: Count
    mean: tuple[Finite, Finite, Finite]
    std: tuple[Positive, Positive, Positive]
    #: "crop": centre crop to a multiple of the patch; "fixed": interpolate to `input_size`
    resize: Literal["crop", "fixed"]
    input_size: tuple[Count, Count] | None = None
    interpolation: Literal["bilinear", "nearest", "bicubic"]
    facets: tuple[Literal["token", "query", "key", "value"], ...]
    preprocess: str                   # the preprocessing's name in fingerprints
    stride: Count | None = None       # default stride of the patch embedding (None: the patch)
    channels: Literal["thirds", "head-interleaved"] = "thirds"
    cls: Literal["final-norm", "layer", "none"]
    normalise_patches: Literal["always", "vlad"]
    licence: str = Field(min_length=1)
    gated: Flag
    page: str = Field(pattern=r"^https://\S+$")
    url: str | None = Field(None, pattern=r"^https://\S+/[^/\s]+$")  # the authors' release file (official format)
    sha256: str | None = Field(None, pattern=r"^[0-9a-fA-F]{64}$")  # only when the authors publish one
    hub: str | None = Field(None, pattern=r"^[A-Za-z0-9_.-]+/[A-Za-z0-9_.-]+$")  # Hugging Face hub repository
    #: the file timm names in the hub repository (its pretrained config's hf_hub_filename, else its default)
    hub_file: str = Field("pytorch_model.bin", pattern=r"^[A-Za-z0-9_.-]+$")
    #: keyword arguments timm's constructor needs (e.g. dynamic_img_size for any input size)
    timm_kwargs: dict[str, bool | int | float | str] = Field(default_factory=dict)
    #: the precision the release keeps its RoPE periods in (DINOv3: bfloat16; timm computes float32)
    rope_periods: Literal["float32", "bfloat16"] = "float32"
    #: the licence timm's pretrained config names the release's weights by: a `timm:` name whose config
    #: says it (another size or variant of the release) is of this release (licence, gating, RoPE periods)
    timm_licence: str | None = Field(None, min_length=1)

    @model_validator(mode="after")
    def _consistent(self):
        if self.resize == "fixed" and self.input_size is None:
            raise ValueError("resize = 'fixed' needs input_size = [HEIGHT, WIDTH]")
        if self.input_size and self.position_interpolation == "timm" and any(s % self.patch for s in self.input_size):
            raise ValueError(f"input_size {self.input_size[0]} x {self.input_size[1]} is not a multiple of the patch "
                             f"{self.patch} (timm's embedding needs one); give multiples of {self.patch}")
        if self.cls == "final-norm" and not self.cls_token:
            raise ValueError("cls = 'final-norm' needs a CLS token")
        if self.url is None and self.hub is None:
            raise ValueError("give a weight source: url (the release) or hub (a Hugging Face repository)")
        if self.stride is not None and self.patch % self.stride:
            raise ValueError(f"stride {self.stride} does not divide the patch {self.patch}; give a divisor of it")
        if "token" not in self.facets or len(set(self.facets)) != len(self.facets):
            raise ValueError(f"facets {list(self.facets)}: list each facet once, 'token' among them "
                             "(every ViT gives it)")
        reserved = sorted(TIMM_RESERVED & set(self.timm_kwargs))
        if reserved:
            raise ValueError(f"timm_kwargs {', '.join(reserved)}: vprbench loads the weights itself (the resolver, "
                             "or random); leave them out")
        return self

    @property
    def prefix_tokens(self) -> int:
        return int(self.cls_token) + self.registers

    @property
    def file_name(self) -> str:
        return self.url.rsplit("/", 1)[-1] if self.url else self.hub_files[0]

    @property
    def hub_files(self) -> tuple[str, ...]:
        """The hub files of the weights in the order timm looks for them (timm.models._hub's
        load_state_dict_from_hf): the .safetensors beside `hub_file` first, then `hub_file` itself."""
        name = self.hub_file
        safe = {"pytorch_model.bin": "model.safetensors", "open_clip_pytorch_model.bin": "open_clip_model.safetensors"}
        alternative = safe.get(name) or (name.removesuffix(".bin") + ".safetensors" if name.endswith(".bin") else None)
        return (alternative, name) if alternative else (name,)

    @property
    def source(self) -> WeightSource:
        """The release URL when there is one, else the hub files (the first found is loaded)."""
        if self.url:
            return WeightSource(self.file_name, url=self.url, page=self.page, sha256=self.sha256, gated=self.gated,
                                licence=self.licence)
        return WeightSource(self.file_name, hub=self.hub, page=self.page, gated=self.gated, licence=self.licence,
                            also_named=self.hub_files[1:])

    @property
    def default_stride(self) -> int:
        """The patch stride it runs at unless told (DINO v1 as AnyLoc: 4)."""
        return self.stride or self.patch

    @property
    def one_stride(self) -> bool:
        """Whether it runs at its patch stride only (timm's own patch embedding takes no other)."""
        return self.position_interpolation == "timm"

    @property
    def feature_variant(self) -> dict[str, str]:
        """What changes its features beyond its name and weights, said only where not the default (other
        backbones' keys stay as they were): RoPE periods other than timm's float32. The one source of the
        descriptor store's key (AnyLoc.fingerprint) and the vocabulary key (vocabulary_key) for it."""
        return {"rope_periods": self.rope_periods} if self.rope_periods != "float32" else {}

    @property
    def timm_name(self) -> str:
        return f"{self.timm}.{self.tag}" if self.tag else self.timm

    def card(self) -> dict:
        """What records say about the backbone: its entry, weights tag, licence and gating."""
        return {"name": self.name, "family": self.family, "timm": self.timm_name, "licence": self.licence,
                "gated": self.gated, **({"access": self.page} if self.gated else {})}


#: what a field with a pattern takes, said in words where a value does not match
WRITTEN_AS = {"name": "a name of letters, digits and . _ : -", "timm": "a timm architecture (letters, digits, _)",
              "tag": "a timm weights tag (letters, digits, _ -)", "page": "an https:// address",
              "url": "an https:// address of a file", "sha256": "a sha256 (64 hexadecimal digits)",
              "hub": "a Hugging Face repository (OWNER/NAME)"}


def _entries(text: str, origin: str) -> list[BackboneEntry]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise VPRBenchError(f"Backbone manifest {origin} is not valid TOML ({error}); fix it.") from None
    defaults = data.get("family", {})
    found = []
    for raw in data.get("backbone", []):
        try:
            found.append(BackboneEntry(**{**defaults, **raw}))
        except ValidationError as error:
            first = error.errors()[0]
            where = f"{'.'.join(map(str, first['loc']))}: " if first["loc"] else ""  # a model check has no field
            said = first["msg"].removeprefix("Value error, ")
            if first["type"] == "string_pattern_mismatch" and first["loc"][0] in WRITTEN_AS:  # not the regex
                said = f"{first['input']!r} is not {WRITTEN_AS[first['loc'][0]]}"
            raise VPRBenchError(f"Backbone manifest {origin}, entry {raw.get('name', '?')!r}: {where}{said}.") from None
    return found


@cache
def backbones() -> dict[str, BackboneEntry]:
    """Every backbone vprbench ships, by name (manifests/backbones/*.toml)."""
    folder = files("vprbench.manifests") / "backbones"
    found: dict[str, BackboneEntry] = {}
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        if path.name.endswith(".toml"):
            for entry in _entries(path.read_text(encoding="utf-8"), path.name):
                if entry.name in found:
                    raise VPRBenchError(f"Backbone {entry.name!r} is listed twice in manifests/backbones.")
                found[entry.name] = entry
    return found


def backbone_spec(name: str) -> BackboneEntry:
    """The manifest entry `name`, or, for `timm:ARCH.TAG`, one built from timm's pretrained config."""
    if not isinstance(name, str):
        raise VPRBenchError(f"backbone takes a name, got {name!r}.")
    if name.startswith(TIMM_PREFIX):
        return timm_entry(name.removeprefix(TIMM_PREFIX))
    known = backbones()
    if name not in known:
        raise VPRBenchError(f"Unknown backbone {name!r}.{closest_names(name, known)} Available: {', '.join(known)}, "
                            "or timm:ARCH.TAG for another timm ViT.")
    return known[name]


def _why_not_a_vit(model) -> str:
    """What in a timm model's structure stops vprbench reading it as a ViT, said of the model itself
    where its parts tell (a patch embedding under another name, blocks of another kind), else the
    general reason. Read from its modules, not its family's name: a new model of the kind is told too."""
    general = ("has no patch tokens vprbench can read (it is not a ViT with a patch embedding, blocks and per-block "
               "tokens, e.g. a CNN, a hybrid or a hierarchical model)")
    embeddings = [m for m in model.children() if isinstance(getattr(m, "patch_size", None), tuple)]
    blocks = getattr(model, "blocks", None)
    blocks = list(blocks.children()) if hasattr(blocks, "children") else []
    if len(embeddings) != 1 or not blocks:
        return general
    kind = type(model).__name__
    attentions = [name for name, m in blocks[0].named_children() if "Attention" in type(m).__name__]
    if len(attentions) > 1 and getattr(blocks[0], "attn", None) is None:  # TNT: inner blocks over each patch's pixels
        return (f"({kind}) embeds each patch as pixel tokens and nests inner pixel blocks in its blocks (attentions "
                f"{', '.join(attentions)}; no single attention over the patch and prefix tokens), so its blocks hand "
                "no plain per-patch tokens")
    if not any("Attention" in type(m).__name__ for m in model.modules()):  # MLP-Mixer, ResMLP, gMLP
        prefix = int(getattr(model, "num_prefix_tokens", 0) or 0) or getattr(model, "cls_token", None) is not None
        return (f"({kind}) has patch tokens but no attention at all (its blocks mix tokens with MLPs: no query, key "
                f"or value to read){'' if prefix else ' and no class token'}")
    return general


@cache
def timm_entry(arch_tag: str) -> BackboneEntry:
    """A timm ViT by name: its patch, prefix tokens and position kind read from the architecture
    (built on the meta device, nothing downloaded), mean/std and hub file from its pretrained config."""
    import timm
    import torch

    if not TIMM_NAME.fullmatch(arch_tag):
        raise VPRBenchError(f"Backbone {TIMM_PREFIX + arch_tag!r} is not a timm model name: give timm:ARCH or "
                            "timm:ARCH.TAG (an architecture of letters, digits and '_', and an optional weights tag), "
                            "e.g. timm:vit_small_patch16_224.dino.")
    arch, _, tag = arch_tag.partition(".")
    if arch not in timm.list_models():
        raise VPRBenchError(f"timm has no architecture {arch!r}.{closest_names(arch, timm.list_models())} Give one "
                            "that timm.list_models() names, as timm:ARCH or timm:ARCH.TAG.")
    try:
        cfg = timm.models.get_pretrained_cfg(arch_tag) if tag else timm.models.get_pretrained_cfg(arch)
    except (RuntimeError, ValueError, KeyError):
        cfg = None
    if tag and cfg is None:
        raise VPRBenchError(f"timm has no weights {tag!r} for {arch}; tags: "
                            f"{', '.join(n.partition('.')[2] for n in timm.list_pretrained(arch + '.*')) or 'none'}.")
    with torch.device("meta"):
        model = timm.create_model(arch, pretrained=False, num_classes=0)
    embed = getattr(model, "patch_embed", None) or getattr(model, "embeds", None)  # NaFlexVit: embeds
    patch = getattr(embed, "patch_size", None)
    patch = (patch, patch) if isinstance(patch, int) and not isinstance(patch, bool) else patch  # XCiT: one int
    intermediates = getattr(model, "forward_intermediates", None)
    # the dense extractor reads a block's tokens, prefix tokens apart, through forward_intermediates; a
    # hybrid's embedding is a CNN stem (its `backbone`), whose stride is not the patch
    if not (isinstance(patch, tuple) and len(patch) == 2 and getattr(embed, "backbone", None) is None
            and hasattr(model, "blocks") and intermediates is not None):
        raise VPRBenchError(f"timm:{arch_tag} {_why_not_a_vit(model)}; AnyLoc aggregates per-patch ViT features: "
                            "choose a plain ViT, e.g. timm:vit_small_patch16_224.dino.")
    if not hasattr(model, "dynamic_img_size") and getattr(embed, "strict_img_size", False):
        height, width = embed.img_size
        raise VPRBenchError(f"timm:{arch_tag} takes {height}x{width} inputs only (its patch embedding has a fixed "
                            "size), but AnyLoc reads each image at its own size cropped to a multiple of the patch: "
                            "choose a timm ViT that takes any size, e.g. timm:vit_small_patch16_224.dino.")
    # a ViT-like model (CaiT, SAM's ViT, ...) whose timm code hands no block tokens with its prefix apart
    if "return_prefix_tokens" not in inspect.signature(intermediates).parameters:
        raise VPRBenchError(f"timm:{arch_tag} ({type(model).__name__}) has patch tokens, but timm gives none of its "
                            "blocks' tokens with its class and register tokens set apart (its forward_intermediates "
                            "takes no return_prefix_tokens), which vprbench reads: choose a timm VisionTransformer, "
                            "Eva or NaFlexVit, e.g. timm:vit_small_patch16_224.dino.")
    attn = getattr(model.blocks[0], "attn", None)
    has_qkv = attn is not None and (getattr(attn, "qkv", None) is not None or getattr(attn, "q_proj", None) is not None)
    cfg = cfg.to_dict() if cfg is not None else {}
    # NaFlexVit keeps its CLS token in its embedding (C-RADIO's CLS and registers: embeds.cls_token, reg_token)
    has_cls = getattr(model, "cls_token", None) is not None or getattr(embed, "cls_token", None) is not None
    prefix = int(getattr(model, "num_prefix_tokens", int(has_cls)))
    hub = cfg.get("hf_hub_id") or None
    tag = tag or str(cfg.get("tag") or "")  # the weights timm resolves to, named in records
    # weights of a shipped entry's release: its licence and gating (read from the model card) and the
    # release's RoPE periods precision, which timm's config does not carry (DINOv3's timm copies are
    # gated too, and run as the release: one architecture and weights, one descriptor, by either name)
    listed = list(backbones().values())
    shipped = next((e for e in listed if (e.timm, e.tag) == (arch, tag) or (hub and e.hub == hub)), None) or \
        next((e for e in listed if e.timm_licence and e.timm_licence == cfg.get("license")), None)
    access = {"licence": shipped.licence, "gated": shipped.gated, "page": shipped.page,
              "rope_periods": shipped.rope_periods} if shipped else {
        "licence": str(cfg.get("license") or "see the model card"), "gated": False,
        "page": f"https://huggingface.co/{hub}" if hub else "https://github.com/huggingface/pytorch-image-models"}
    return BackboneEntry(
        name=TIMM_PREFIX + arch_tag, family="timm", timm=arch, tag=tag, patch=int(patch[0]),
        cls_token=has_cls, registers=prefix - int(has_cls),
        position="rope" if getattr(model, "rope", None) is not None else "learned", position_interpolation="timm",
        depth=len(model.blocks), width=int(model.embed_dim),
        mean=tuple(cfg.get("mean", IMAGENET[0])), std=tuple(cfg.get("std", IMAGENET[1])),
        resize="crop", interpolation="bilinear", facets=("token", "query", "key", "value") if has_qkv else ("token",),
        preprocess="crop-to-patch", cls="final-norm" if has_cls else "none", normalise_patches="always",
        timm_kwargs={"dynamic_img_size": True} if hasattr(model, "dynamic_img_size") else {},
        **access, url=None if hub else (cfg.get("url") or None),
        hub=hub or (None if cfg.get("url") else f"timm/{arch_tag}"),
        **({"hub_file": cfg["hf_hub_filename"]} if cfg.get("hf_hub_filename") else {}),
    )
