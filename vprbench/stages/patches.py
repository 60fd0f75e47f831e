"""Dense patch matching on a foundation backbone's per-patch features: mutual nearest neighbours.

Per query and candidate: the patch features of one block and facet of the backbone the user
names (AnyLoc's extraction: `vprbench.methods.anyloc.AnyLoc`, its preprocessing, per-dataset
resize, dense extractor and weights), L2-normalised; a query patch and a candidate patch match
when each is the other's nearest neighbour by cosine similarity (optionally at least
`min_similarity`). A candidate's score is its number of mutual nearest neighbours; equal counts
keep their retrieval order. Each image's patches are computed once and kept in the feature
store (float16), keyed by everything that produced them (backbone, weights by content, layer,
facet, stride, resize, preprocessing), so a second run computes none and never loads the model.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from ..errors import VPRBenchError
from .base import Candidates, RerankOptions, Stage, StageContext, rerank_by_counts

#: AnyLoc's default: DINOv2 ViT-G/14, value facet of block 31; other backbones take the block at the
#: same relative depth unless `layer` is given
DEFAULT_BACKBONE, DEFAULT_LAYER = "dinov2_vitg14", "dinov2_vitg14:31"
#: version of what is stored per image (bump when a change here changes the stored patches)
PATCHES_VERSION = 1


def _backbone(name: str):
    from ..features.catalogue import backbone_spec

    try:
        return backbone_spec(name)
    except VPRBenchError as error:
        raise ValueError(str(error)) from None


class PatchMNNOptions(RerankOptions):
    backbone: str = DEFAULT_BACKBONE
    #: a checkpoint in the official format (a file, or a folder holding the release's file), "random"
    #: (a seeded random initialisation: a pipeline check, never a result), or unset: the authors' release
    weights: str | None = None
    #: 0-based block; unset: AnyLoc's block 31 of ViT-G/14 at the same relative depth
    layer: int | None = Field(None, ge=0)
    facet: str = "value"
    #: HEIGHTxWIDTH before the crop to whole patches, or "native" (no resize); unset: AnyLoc's
    #: per-dataset resize (native size when none)
    resize: tuple[int, int] | Literal["native"] | None = None
    #: a mutual match counts only when its cosine similarity is at least this; unset: every mutual match
    min_similarity: float | None = Field(None, ge=-1, le=1)

    @field_validator("backbone")
    @classmethod
    def _known(cls, name: str) -> str:
        _backbone(name)
        return name

    @field_validator("resize", mode="before")
    @classmethod
    def _size(cls, value):
        from ..features.resize import asks_native, parse_size

        try:
            return "native" if asks_native(value) else parse_size(value)
        except VPRBenchError as error:
            raise ValueError(str(error).removeprefix("Option resize ")) from None

    @model_validator(mode="before")
    @classmethod
    def _default_layer(cls, data):
        """The layer stored resolved, so `layer` unset and the block it stands for are one run."""
        if isinstance(data, dict) and data.get("layer") is None and isinstance(data.get("backbone", DEFAULT_BACKBONE), str):
            try:
                depth = _backbone(data.get("backbone", DEFAULT_BACKBONE)).depth
            except ValueError:
                return data  # the backbone's own check names it
            reference, _, layer = DEFAULT_LAYER.partition(":")
            data = {**data, "layer": round(int(layer) * (depth - 1) / (_backbone(reference).depth - 1))}
        return data

    @model_validator(mode="after")
    def _fits_backbone(self):
        from ..features.dense import FACETS

        spec = _backbone(self.backbone)
        if self.layer is not None and self.layer >= spec.depth:
            raise ValueError(f"layer {self.layer} is out of range for {self.backbone}: it has {spec.depth} blocks, "
                             f"0..{spec.depth - 1} (0-based)")
        if self.facet not in FACETS or self.facet not in spec.facets:
            raise ValueError(f"facet {self.facet!r}: {self.backbone} gives {', '.join(spec.facets)}; choose one of those")
        if self.weights is not None and self.weights != "random" and not Path(self.weights).expanduser().exists():
            raise ValueError(f"weights file {self.weights} does not exist: give a checkpoint of {self.backbone} in the "
                             "official format, 'random' (a pipeline check), or leave it unset for the authors' release")
        return self


def mutual_matches(query: np.ndarray, candidate: np.ndarray, min_similarity: float | None = None) -> int:
    """How many patches of `query` (n, d) and `candidate` (m, d), unit rows, are each other's nearest
    neighbour by cosine similarity (the first on a tie), at least `min_similarity` when given.

    Float64: a product of two float16 values is exact in it and the sums round far below any gap
    between two similarities, so the nearest neighbours do not depend on the CPU or BLAS."""
    similarity = np.asarray(query, np.float64) @ np.asarray(candidate, np.float64).T
    forward = similarity.argmax(axis=1)
    mutual = similarity.argmax(axis=0)[forward] == np.arange(len(query))
    if min_similarity is not None:
        mutual &= similarity[np.arange(len(query)), forward] >= min_similarity
    return int(np.count_nonzero(mutual))


class PatchMNN(Stage):
    track = "re-ranked"
    Options = PatchMNNOptions
    description = "mutual nearest neighbours between per-patch features of an AnyLoc backbone/layer/facet"

    def __init__(self, options=None):
        super().__init__(options)
        self._method = None

    def extractor(self, context: StageContext | None = None):
        """AnyLoc with this stage's backbone, weights, layer and facet: its preprocessing, resize rule and
        dense extractor; the model itself loads only when a patch is computed."""
        if self._method is None:
            from ..methods.anyloc import AnyLoc

            o = self.options
            device = context.device if context is not None else "cpu"
            cache_dir = context.cache_dir if context is not None else None
            self._method = AnyLoc(backbone=o.backbone, weights=o.weights, layer=o.layer, facet=o.facet,
                                  aggregation="gap", resize=o.resize, device=device, cache_dir=cache_dir, batch_size=1)
        if context is not None:
            self._method.use_dataset(context.dataset.name)
        return self._method

    def feature_identity(self, context: StageContext) -> dict:
        from ..images import ORIENTATION
        from ..methods.anyloc import DESCRIPTOR_VERSION

        fingerprint = self.extractor(context).fingerprint()
        return {"extractor": "anyloc-dense", "version": PATCHES_VERSION, "anyloc": DESCRIPTOR_VERSION,
                **{k: fingerprint[k] for k in ("backbone", "weights", "layer", "facet", "stride", "resize", "preprocess")},
                "normalised": "l2", "dtype": "float16", "decoding": ORIENTATION}

    def _named(self, error: VPRBenchError) -> VPRBenchError:
        """The weights resolver's message, naming this stage and the option that takes a file."""
        return VPRBenchError(f"Stage {self.name!r}: {str(error).replace('--weights PATH', '--rerank-option weights=PATH')}")

    def _store(self, context: StageContext):
        try:
            identity = self.feature_identity(context)
        except VPRBenchError as error:
            raise self._named(error) from None
        # (N, width) float16 per image, as `patches` gives them (a facet is as wide as the backbone, as
        # AnyLoc's vocabularies are checked): a stored image that is not is recomputed
        form = {"patches": ("float16", (self.extractor(context).spec.width,))}
        return context.features("patches", identity, form)

    def patches(self, path) -> dict[str, np.ndarray]:
        """One image's (N, D) unit patch features, float16, as stored."""
        import torch.nn.functional as F

        try:
            self._method.extractor  # the model, loaded on the first image computed
        except VPRBenchError as error:
            raise self._named(error) from None
        found = next(iter(self._method.iter_patch_features([path])))
        return {"patches": F.normalize(found.float(), dim=-1).numpy().astype(np.float16)}

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        threshold = self.options.min_similarity
        return rerank_by_counts(self.name, candidates, context, self._store(context), self.patches,
                                lambda query, other: mutual_matches(query, other["patches"], threshold),
                                prepare=lambda query: query["patches"].astype(np.float64))

    def stored_bytes(self, context: StageContext) -> int:
        return int(self._store(context).bytes_per_image("database") * context.database.row_count)

    def provenance(self) -> dict:
        from ..weights import weights_provenance

        method = self.extractor()
        return {"weights": weights_provenance(method.weights_identity()), "backbone": method.spec.card()}
