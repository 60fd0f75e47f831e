"""AnyLoc (Keetha et al., RA-L 2023): dense self-supervised ViT features + VLAD/GeM.

One implementation, a composition of backbone x layer/facet x aggregation x vocabulary x
PCA; the paper's variants are presets (data in manifests/methods/anyloc.toml).
"""
from __future__ import annotations

import hashlib
import warnings
import tomllib
from collections.abc import Sequence
from importlib.resources import files
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..aggregation import pooling, vlad
from ..aggregation.pca import PCAWhitening
from ..aggregation.policies import paper_vocabulary, resolve_vocabulary, vocabulary_images
from ..aggregation.vlad import vlad_hard
from ..aggregation.vocabulary import fit_vocabulary
from ..errors import VPRBenchError
from ..features.backbones import backbone_spec, load_backbone, weights_identity
from ..weights import weights_provenance
from ..features.dense import FACETS, DenseExtractor
from ..features.preprocess import dataset_resize, parse_size, preprocess
from .base import Method, l2_normalise
from .registry import register_method

#: bump when a change in this code changes descriptors (part of the fingerprint)
DESCRIPTOR_VERSION = 1
AGGREGATIONS = ("vlad", "vlad-soft-official", "vlad-soft", "gem", "gap", "gmp", "cls")
VLADS = ("vlad", "vlad-soft-official", "vlad-soft")
PRECISIONS = {"fp32": None, "fp16": torch.float16, "bf16": torch.bfloat16}


def _aggregate(name: str, feats: torch.Tensor, centres: torch.Tensor | None, gem_p: float) -> torch.Tensor:
    if name == "vlad":
        return vlad_hard(feats, centres)
    if name == "vlad-soft-official":
        return vlad.vlad_soft_official(feats, centres)
    if name == "vlad-soft":
        return vlad.vlad_soft(feats, centres)
    if name == "gem":
        return pooling.gem(feats, gem_p)
    return getattr(pooling, name)(feats)


class AnyLoc(Method):
    """Global descriptors from one block/facet of DINOv2 or DINO, aggregated."""

    def __init__(self, *, backbone: str = "dinov2_vitg14", weights: str | None = None, layer: int | None = None,
                 layer_for: str = "dinov2_vitg14:31",
                 facet: str = "value", aggregation: str = "vlad", clusters: int = 32,
                 vocabulary: str = "map", resize=None, pca_dim: int | None = None, batch_size: int = 8,
                 precision: str = "fp32", device: str = "cpu", dataset: str | None = None,
                 stride: int | None = None, gem_p: float = 3.0):
        self.spec = backbone_spec(backbone)
        self.family = self.spec.family
        if aggregation not in AGGREGATIONS:
            raise VPRBenchError(f"Unknown aggregation {aggregation!r}: use one of {', '.join(AGGREGATIONS)}.")
        if facet not in FACETS:
            raise VPRBenchError(f"Unknown facet {facet!r}: use one of {', '.join(FACETS)}.")
        if precision not in PRECISIONS:
            raise VPRBenchError(f"Unknown precision {precision!r}: use fp32, fp16 or bf16.")
        self.device = torch.device(device)
        if precision != "fp32" and self.device.type != "cuda":
            raise VPRBenchError(f"precision={precision} needs a CUDA device; on {device} use fp32.")
        if int(batch_size) < 1:
            raise VPRBenchError(f"batch_size must be at least 1, got {batch_size}")
        if aggregation in VLADS and int(clusters) < 1:
            raise VPRBenchError(f"clusters must be at least 1, got {clusters}")
        self.backbone, self.weights, self.facet = backbone, weights, facet
        if layer is not None:
            self.layer = int(layer)
        elif aggregation == "cls" and self.family == "dinov2":
            self.layer = self.spec.depth - 1  # the CLS comes from the final norm: no layer to choose
        else:
            self.layer = self._preset_layer(layer_for)
        self.aggregation, self.clusters, self.vocabulary = aggregation, int(clusters), str(vocabulary)
        self.user_resize = parse_size(resize)
        self.pca_dim = int(pca_dim) if pca_dim else None
        self.batch_size, self.precision, self.dataset = int(batch_size), precision, dataset
        # DINO v1 follows the official dino extractor: stride 4, interleaved heads, raw features
        self.stride = int(stride) if stride else (4 if self.family == "dino" else self.spec.patch)
        self.gem_p = float(gem_p)
        self.centres: torch.Tensor | None = None
        self._extractor: DenseExtractor | None = None
        self._weights_id: str | None = None
        self.needs_fit = aggregation in VLADS and self.vocabulary == "map"
        if aggregation in VLADS and self.vocabulary != "map":
            self.centres = self._resolve_vocabulary()

    # ------------------------------------------------------------ configuration
    def _preset_layer(self, layer_for: str) -> int:
        """A preset's layer is given for its own backbone ("dinov2_vitg14:31"); on another
        backbone without --layer, the block at the same relative depth is used, and said."""
        reference, _, layer = layer_for.partition(":")
        depth, reference_depth = self.spec.depth, backbone_spec(reference).depth
        if depth == reference_depth:
            return int(layer)
        chosen = round(int(layer) * (depth - 1) / (reference_depth - 1))
        warnings.warn(f"layer {layer} is {reference}'s ({reference_depth} blocks); on {self.backbone} "
                      f"({depth} blocks) block {chosen} at the same relative depth is used. Pass --layer to choose.",
                      stacklevel=2)
        return chosen

    def use_dataset(self, name: str) -> None:
        """Tell the method which dataset it runs on (AnyLoc's per-dataset resize, domain vocabularies)."""
        self.dataset = name
        if self.aggregation in VLADS and self.vocabulary == "domain":
            self.centres = self._resolve_vocabulary()

    @property
    def resize(self) -> tuple[int, int] | None:
        return self.user_resize if self.user_resize is not None else dataset_resize(self.dataset)

    @property
    def normalise_patches(self) -> bool:
        # DINOv2 extractor normalises every patch; for DINO v1 only the official VLAD does
        return self.family == "dinov2" or self.aggregation in VLADS

    def _resolve_vocabulary(self) -> torch.Tensor | None:
        """Centres for a vocabulary option other than "map": a file/folder path, a cached
        source name (a domain such as "indoor", or "map-<dataset>"), or "domain" = the
        vocabulary the paper uses for the current dataset."""
        spec = self.vocabulary
        if spec == "domain":
            if self.dataset is None:
                return None  # resolved in use_dataset()
            spec = paper_vocabulary(self.dataset)
        found = resolve_vocabulary(spec, self.backbone, self.layer, self.facet, self.clusters)
        return found.centres.float()

    # ------------------------------------------------------------ identity
    def weights_identity(self) -> str:
        if self._weights_id is None:
            self._weights_id = weights_identity(self.spec, self.weights)
        return self._weights_id

    def fingerprint(self) -> dict:
        fp = {
            "method": "anyloc", "descriptor_version": DESCRIPTOR_VERSION,
            "backbone": self.backbone, "weights": self.weights_identity(),
            "layer": self.layer, "facet": self.facet, "aggregation": self.aggregation,
            "preprocess": f"{self.family}-official", "stride": self.stride,
            "resize": list(self.resize) if self.resize else "native", "precision": self.precision,
        }
        if self.aggregation == "cls" and self.family == "dinov2":
            fp["layer"], fp["facet"] = "final-norm", "cls"  # layer/facet options do not apply
        if self.aggregation in VLADS:
            fp["clusters"] = self.clusters
            # a named or file vocabulary is identified by its centres' bytes
            fp["vocabulary"] = "map" if self.vocabulary == "map" else (
                "sha256:" + hashlib.sha256(self.centres.numpy().tobytes()).hexdigest()
                if self.centres is not None else self.vocabulary)
        if self.aggregation == "gem":
            fp["gem_p"] = self.gem_p
        if self.pca_dim:
            fp["pca_dim"] = self.pca_dim
        return fp

    def provenance(self) -> dict:
        found = {"weights": weights_provenance(self.weights_identity())}
        if self.aggregation in VLADS:
            found["vocabulary"] = {"source": self.vocabulary, "fitted_on_evaluated_database": self.needs_fit}
        if self.pca_dim:
            found["pca"] = {"dim": self.pca_dim, "fitted_on_evaluated_database": True}
        return found

    # ------------------------------------------------------------ extraction
    @property
    def extractor(self) -> DenseExtractor:
        if self._extractor is None:
            model, spec, identity = load_backbone(self.backbone, self.weights, self.device)
            self._weights_id = identity
            layer, facet = self.layer, self.facet
            if self.aggregation == "cls" and self.family == "dinov2":
                layer, facet = len(model.blocks) - 1, "token"  # CLS comes from the final norm
            self._extractor = DenseExtractor(model, spec, layer, facet, stride=self.stride,
                                             head_interleaved=self.family == "dino")
        return self._extractor

    def _batches(self, images: Sequence[Path], resize: tuple[int, int] | None = None):
        """(indices, batch tensor): runs of consecutive same-sized preprocessed images, at most
        batch_size each, in input order (so streams, e.g. vocabulary sampling, never depend on
        the batch size)."""
        resize = parse_size(resize) or self.resize
        group: list[tuple[int, torch.Tensor]] = []
        for i, path in enumerate(images):
            x = preprocess(path, family=self.family, patch=self.spec.patch, resize=resize)
            if group and (len(group) == self.batch_size or group[0][1].shape != x.shape):
                yield [j for j, _ in group], torch.stack([t for _, t in group])
                group = []
            group.append((i, x))
        if group:
            yield [j for j, _ in group], torch.stack([t for _, t in group])

    def _autocast(self):
        dtype = PRECISIONS[self.precision]
        return torch.autocast("cuda", dtype=dtype) if dtype is not None else torch.autocast("cpu", enabled=False)

    def patch_features(self, batch: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) -> (B, N, D) float32 patch features, L2-normalised on the DINOv2 path."""
        with self._autocast():
            feats = self.extractor(batch.to(self.device)).float()
        return F.normalize(feats, dim=-1) if self.normalise_patches else feats

    def _global(self, batch: torch.Tensor) -> torch.Tensor:
        if self.aggregation == "cls":
            with self._autocast():
                if self.family == "dinov2":
                    return self.extractor.cls_token(batch.to(self.device)).float()
                return self.extractor(batch.to(self.device), keep_prefix=True)[:, 0].float()
        feats = self.patch_features(batch)
        centres = None
        if self.aggregation in VLADS:
            if self.centres is None:
                raise VPRBenchError("AnyLoc VLAD needs a vocabulary: call fit() on the database first"
                                    + (" or use_dataset() for vocabulary=domain." if self.vocabulary == "domain" else "."))
            centres = self.centres.to(feats.device)
        return _aggregate(self.aggregation, feats, centres, self.gem_p)

    def describe(self, images: Sequence[Path]) -> np.ndarray:
        out: np.ndarray | None = None
        for indices, batch in self._batches(images):
            desc = self._global(batch).cpu().numpy()
            if out is None:
                out = np.zeros((len(images), desc.shape[1]), dtype=np.float32)
            out[indices] = desc
        if out is None:
            return np.zeros((0, 0), dtype=np.float32)
        return l2_normalise(out)

    # ------------------------------------------------------------ vocabulary
    def fit(self, database: Sequence[Path]) -> None:
        if not self.needs_fit:
            return
        if self.dataset is not None:  # as the authors: no distractors, the dataset's stride
            database = vocabulary_images(self.dataset, database)
        # one image's features at a time into the bounded-memory sampler of fit_vocabulary
        self.centres = fit_vocabulary(self.iter_patch_features(database), self.clusters).centres.float()

    def iter_patch_features(self, paths: Sequence[Path], resize=None):
        """Each image's (N, D) patch features as they enter VLAD, in input order.
        `resize` (H, W) overrides the method's resize (domain vocabularies use 320x320)."""
        for _, batch in self._batches(paths, resize):
            yield from self.patch_features(batch).cpu()

    def fit_state(self) -> dict[str, np.ndarray]:
        return {"centres": self.centres.cpu().numpy()} if self.needs_fit and self.centres is not None else {}

    def load_fit_state(self, state: dict[str, np.ndarray]) -> None:
        if "centres" in state:
            self.centres = torch.from_numpy(np.asarray(state["centres"], dtype=np.float32))

    # ------------------------------------------------------------ PCA-whitening
    def postprocessor(self) -> PCAWhitening | None:
        """The -PCA presets: whitening fitted on the database descriptors (output L2-normalised)."""
        return PCAWhitening(self.pca_dim) if self.pca_dim else None


# ---------------------------------------------------------------- presets
def presets() -> dict[str, dict]:
    """Preset name -> {"description": ..., "options": {...}} from manifests/methods/anyloc.toml."""
    text = (files("vprbench.manifests") / "methods" / "anyloc.toml").read_text()
    return tomllib.loads(text)["presets"]


def register() -> None:
    for name, preset in presets().items():
        register_method(name, AnyLoc, defaults=preset.get("options", {}), description=preset.get("description", ""))
    register_method("anyloc", AnyLoc, description="AnyLoc composition; every option settable (see docs/anyloc.md)")
