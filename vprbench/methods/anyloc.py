"""AnyLoc (Keetha et al., RA-L 2023): dense self-supervised ViT features + VLAD/GeM.

One implementation, a composition of backbone x layer/facet x aggregation x vocabulary x
PCA; the paper's variants are presets (data in manifests/methods/anyloc.toml).
"""
from __future__ import annotations

import hashlib
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..aggregation import pooling, vlad
from ..aggregation.pca import PCAWhitening
from . import anyloc_options
from .anyloc_options import AGGREGATIONS, PCA_ON, VLADS, pca_datasets, pca_provenance
from .anyloc_fit import recorded_image_digests
from .anyloc_provenance import (SAMPLING_KEYS, check_released_setting, counts_of_state, counts_state, file_provenance,
                                release_status)
from .anyloc_lookup import check_proven, fit_options, paper_choice, resolve_vocabulary
from .anyloc_vocabulary import MAP_PREFIX, names_file, vocabulary_images
from ..aggregation.vlad import vlad_hard
from ..aggregation.kmeans import DEFAULT_BUDGET
from ..aggregation.vocabulary import fit_vocabulary
from ..errors import VPRBenchError
from ..features.backbones import RANDOM, backbone_spec, load_backbone, weights_identity
from ..weights import cached_weights, file_sha256, weights_provenance
from ..features.dense import FACETS, DenseExtractor, patch_grid
from ..features.preprocess import crop_offsets, preprocess
from ..features.resize import asks_native, dataset_resize, parse_size
from ..loader import loaded
from .base import Method, fitted_centres, l2_normalise
from .checks import choice, number, text, whole
from .checks import device as check_device

#: bump when a change in this code changes descriptors (part of the fingerprint)
DESCRIPTOR_VERSION = 1
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

    dataset_option = "dataset"  # picks the resize and domain vocabulary; unset, the dataset evaluated does

    def __init__(self, *, backbone: str = "dinov2_vitg14", weights: str | None = None, layer: int | None = None,
                 layer_for: str = "dinov2_vitg14:31",
                 facet: str = "value", aggregation: str = "vlad", clusters: int = 32,
                 vocabulary: str = "map", resize=None, pca_dim: int | None = None, pca_on: str = "database", batch_size: int = 8,
                 precision: str = "fp32", device: str = "cpu", dataset: str | None = None,
                 stride: int | None = None, gem_p: float = 3.0, cache_dir=None):
        # every option is checked here, before weights or vocabularies are touched
        self.cache_dir = cache_dir  # where weights and vocabularies are found (not an option: no identity)
        self.spec = backbone_spec(text("anyloc", "backbone", backbone))
        aggregation = choice("anyloc", "aggregation", aggregation, AGGREGATIONS)
        facet = choice("anyloc", "facet", facet, FACETS)
        precision = choice("anyloc", "precision", precision, tuple(PRECISIONS))
        self.device = torch.device(check_device("anyloc", device))
        if precision != "fp32" and self.device.type != "cuda":
            raise VPRBenchError(f"precision={precision} needs a CUDA device; on {device} use fp32.")
        self.backbone, self.facet = backbone, facet
        if isinstance(weights, Path):
            weights = str(weights)
        self.weights = None if weights is None else text("anyloc", "weights", weights, "a checkpoint file in the official format")
        self.aggregation = aggregation
        self.clusters = whole("anyloc", "clusters", clusters, 1, what="VLAD vocabulary size")
        self.vocabulary = text("anyloc", "vocabulary", vocabulary, "map, domain, a domain name or a file")
        self.user_resize = parse_size(resize)
        self.native = asks_native(resize)  # "native": no resize, not "unset" (the per-dataset policy)
        self.pca_dim = None if pca_dim is None else whole("anyloc", "pca_dim", pca_dim, 1, what="PCA output dimension; leave it unset for none")
        self.pca_on = choice("anyloc", "pca_on", pca_on, PCA_ON)
        self.batch_size = whole("anyloc", "batch_size", batch_size, 1, what="images per batch")
        self.precision = precision
        self.dataset = self.given_dataset = None if dataset is None else text("anyloc", "dataset", dataset)
        # DINO v1 follows the official dino extractor: stride 4, interleaved heads, raw features
        self.stride = whole("anyloc", "stride", stride, 1, self.spec.patch, f"pixels, at most the patch size {self.spec.patch}") \
            if stride is not None else self.spec.default_stride
        patch = self.spec.patch
        if self.stride != patch and self.spec.one_stride:
            raise VPRBenchError(f"anyloc: option stride={self.stride}: backbone {backbone} runs at its patch stride "
                                f"{patch} only; leave stride unset or give {patch}.")
        if patch % self.stride:
            divisors = ", ".join(str(d) for d in range(1, patch + 1) if patch % d == 0)
            raise VPRBenchError(f"anyloc: option stride={self.stride} does not divide the patch {patch} of "
                                f"{backbone}; give one of {divisors}.")
        self.gem_p = number("anyloc", "gem_p", gem_p, above=0, what="GeM's power, e.g. 3")
        if facet not in self.spec.facets and aggregation != "cls":
            raise VPRBenchError(f"facet={facet}: backbone {backbone} gives {', '.join(self.spec.facets)} only (its attention "
                                "has no separate query/key/value); choose one of those.")
        if aggregation == "cls" and self.spec.cls == "none":
            raise VPRBenchError(f"aggregation=cls: backbone {backbone} has no CLS token (its prefix tokens: "
                                f"{self.spec.prefix_tokens}); use gem, vlad or another pooling.")
        if layer is not None:
            self.layer = whole("anyloc", "layer", layer, 0, self.spec.depth - 1, f"0-based block of {backbone}")
        elif aggregation == "cls" and self.spec.cls == "final-norm":
            self.layer = self.spec.depth - 1  # the CLS comes from the final norm: no layer to choose
        else:
            self.layer = self._preset_layer(text("anyloc", "layer_for", layer_for, "BACKBONE:LAYER"))
        self.centres: torch.Tensor | None = None
        self._extractor: DenseExtractor | None = None
        self._weights_id: str | None = None
        #: where the centres came from, for provenance(): name, source, file, sha256, note
        self.vocabulary_info: dict = {}
        self.fitted_digests: set[str] = set()  # of the images an own folder's map vocabulary was fitted on
        self.fit_counts: dict = {}  # features seen and used by this run's fit (a fit read back from its store: kept there)
        # "domain" (the paper's choice per dataset) is settled in use_dataset; until then, fit on the database
        self.needs_fit = aggregation in VLADS and self.vocabulary in ("map", "domain")
        if aggregation in VLADS and self.vocabulary not in ("map", "domain"):
            self.centres = self._resolve_vocabulary()

    # what a run's spec asks of the options before the method is created (anyloc_options.py)
    cached_identities = classmethod(anyloc_options.cached_identities)
    implied_options = classmethod(anyloc_options.implied_options)
    unused_options = classmethod(anyloc_options.unused_options)

    # ------------------------------------------------------------ configuration
    def _preset_layer(self, layer_for: str) -> int:
        """A preset's layer is given for its own backbone ("dinov2_vitg14:31"); on another
        backbone without --layer, the block at the same relative depth is used, and said."""
        reference, _, layer = layer_for.partition(":")
        depth, reference_depth = self.spec.depth, backbone_spec(reference).depth
        layer = whole("anyloc", "layer_for", layer, 0, reference_depth - 1, f"BACKBONE:LAYER, a block of {reference}")
        if depth == reference_depth:
            return int(layer)
        chosen = round(int(layer) * (depth - 1) / (reference_depth - 1))
        warnings.warn(f"layer {layer} is {reference}'s ({reference_depth} blocks); on {self.backbone} "
                      f"({depth} blocks) block {chosen} at the same relative depth is used (--layer chooses another).",
                      stacklevel=2)
        return chosen

    def use_dataset(self, name: str) -> None:
        """Tell the method which dataset it runs on (AnyLoc's per-dataset resize, domain vocabularies)."""
        if self.given_dataset not in (None, name):  # else evaluated with another dataset's settings, named so
            raise VPRBenchError(f"anyloc: option dataset={self.given_dataset!r} names another dataset than the one "
                                f"evaluated ({name!r}), whose settings apply: drop it (it is for describing images "
                                "outside an evaluation; choose a size with --resize).")
        self.dataset = name
        if self.aggregation in VLADS and self.vocabulary == "domain":
            found, source, note = paper_choice(name, self.vocabulary_backbone, self.layer, self.facet, self.clusters,
                                               self.cache_dir, self.stride)
            if found is not None:
                found.check_dim(self.spec.width)  # before the model loads, naming the file
                check_proven(found, self.vocabulary_backbone, self.layer, self.facet, self.stride)
            self.needs_fit = found is None
            self.centres = None if found is None else found.centres.float()
            self.vocabulary_info = {"name": source, **({"note": note} if note else {}), **(
                {**file_provenance(found), **self._release_status(source, found)} if found is not None else {})}
            if note:
                warnings.warn(note, stacklevel=2)

    @property
    def vocabulary_backbone(self) -> str:
        """The backbone name vocabularies are keyed by. Random weights and a user's own checkpoint
        (not the authors' release) get their own key, BACKBONE@random and BACKBONE@<16 hex of its
        sha256>: centres fitted on their features never serve other weights' features."""
        if self.weights == RANDOM:
            return f"{self.backbone}@{RANDOM}"
        identity = self.weights_identity()  # a file in the cache vprbench did not download is the user's too
        if identity is not None and weights_provenance(identity)["source"] == "user":
            return f"{self.backbone}@{identity.removeprefix('sha256:')[:16]}"
        return self.backbone

    @property
    def resize(self) -> tuple[int, int] | None:
        if self.user_resize is not None or self.native:
            return self.user_resize
        return dataset_resize(self.dataset)

    @property
    def normalise_patches(self) -> bool:
        # DINOv2 extractor normalises every patch; for DINO v1 only the official VLAD does
        return self.spec.normalise_patches == "always" or self.aggregation in VLADS

    def _resolve_vocabulary(self) -> torch.Tensor:
        """Centres for a vocabulary option other than "map"/"domain": a file/folder path or a
        cached source name (a domain such as "indoor", or "map-<dataset>"); the authors'
        released centres are downloaded on first use where they fit these features."""
        found = resolve_vocabulary(self.vocabulary, self.vocabulary_backbone, self.layer, self.facet, self.clusters,
                                   self.cache_dir, self.stride, fit_options(self))
        found.check_dim(self.spec.width)  # before the model loads, naming the file
        if names_file(self.vocabulary):  # a path: the user vouches for what its metadata does not say
            found.check_setting(self.vocabulary_backbone, self.layer, self.facet, self.stride)
            check_released_setting(found, self.vocabulary_backbone, self.layer, self.facet, self.stride)
        else:  # served by its key: only for the features it proves it was fitted on
            check_proven(found, self.vocabulary_backbone, self.layer, self.facet, self.stride)
        self.vocabulary_info = {"name": self.vocabulary, **file_provenance(found),
                                **({} if names_file(self.vocabulary) else self._release_status(self.vocabulary, found))}
        self.fitted_digests = recorded_image_digests(found)
        return found.centres.float()

    def _release_status(self, name: str, found) -> dict:
        return release_status(name, found, self.vocabulary_backbone, self.layer, self.facet, self.clusters, self.stride)

    # ------------------------------------------------------------ identity
    def weights_identity(self) -> str:
        if self._weights_id is None:
            self._weights_id = weights_identity(self.spec, self.weights, self.cache_dir)
        return self._weights_id

    def fingerprint(self) -> dict:
        fp = {
            "method": "anyloc", "descriptor_version": DESCRIPTOR_VERSION,
            "backbone": self.backbone, "weights": self.weights_identity(),
            "layer": self.layer, "facet": self.facet, "aggregation": self.aggregation,
            "preprocess": self.spec.preprocess, "stride": self.stride,
            "resize": list(self.resize) if self.resize else "native", "precision": self.precision,
        }
        if self.aggregation == "cls" and self.spec.cls == "final-norm":
            fp["layer"], fp["facet"] = "final-norm", "cls"  # layer/facet options do not apply
        fp.update(self.spec.feature_variant)  # RoPE periods: a timm: name of DINOv3 ran timm's float32 before
        if self.aggregation in VLADS:
            fp["clusters"] = self.clusters
            # a named or file vocabulary is identified by its centres' bytes; fitted ones by "map"
            fp["vocabulary"] = "map" if self.needs_fit else (
                "sha256:" + hashlib.sha256(self.centres.numpy().tobytes()).hexdigest()
                if self.centres is not None else self.vocabulary)
        if self.aggregation == "gem":
            fp["gem_p"] = self.gem_p
        if self.pca_dim:
            fp["pca_dim"] = self.pca_dim
            if self.pca_on != "database":  # unset, the key of the stores and records made before the option
                fp["pca_on"] = self.pca_on
        return fp

    def provenance(self) -> dict:
        found = {"weights": self.weights_provenance(), "backbone": self.spec.card()}
        if self.aggregation in VLADS:
            found["vocabulary"] = self.vocabulary_provenance()
        if self.pca_dim:
            found["pca"] = pca_provenance(self.pca_dim, self.pca_on, self.dataset)
        return found

    def weights_provenance(self) -> dict:
        """Where the weights came from; a downloaded release also by the sha256 of the file used
        (a local file is identified by it already)."""
        found = weights_provenance(self.weights_identity())
        if found.get("source") == "official" and "sha256" not in found:
            downloaded = cached_weights(self.spec.source, self.cache_dir)
            if downloaded is not None:
                found["sha256"] = file_sha256(downloaded)
        return found

    def vocabulary_provenance(self) -> dict:
        """Which vocabulary, its source and sha256, and whether it was fitted on the evaluated database."""
        info = {"option": self.vocabulary, **self.vocabulary_info, "fitted_on_evaluated_database": self.needs_fit}
        datasets = self.vocabulary_info.get("datasets") or []
        if not self.needs_fit and "folder" in self.vocabulary_info:  # a folder of one's own's: two may share a name,
            # so it is known by its images (fitted_image_digests), unknown where its fit did not record them
            info["fitted_on_evaluated_database"] = False if self.fitted_digests else None
        elif not self.needs_fit and self.dataset in datasets:  # map-<dataset>, or a domain holding the dataset
            info.update(fitted_on_evaluated_database=True,
                        fitted_on=" + ".join(f"the database of {name}" for name in datasets))
        if self.needs_fit:
            info.update(source="fitted", name=f"{MAP_PREFIX}{self.dataset}" if self.dataset else "map",
                        fitted_on=f"the database of {self.dataset}" if self.dataset else "the database given to fit()")
            info.pop("file", None)
            # the paper's k-means sees every patch of the database; a run's fit a seeded sample (fit below)
            info["sampling"] = {"exact": False, "budget": DEFAULT_BUDGET, **self.fit_counts}
        if self.centres is not None:
            info["centres_sha256"] = hashlib.sha256(self.centres.numpy().tobytes()).hexdigest()
            info["clusters"], info["dim"] = int(self.centres.shape[0]), int(self.centres.shape[1])
        return info

    def fitted_image_digests(self) -> dict[str, set[str]]:
        """The record marks the vocabulary fitted on the evaluated database when these are its images."""
        return {"vocabulary": self.fitted_digests} if self.fitted_digests else {}

    # ------------------------------------------------------------ extraction
    def prepare(self) -> None:
        self.patches_per_image()  # a resize below one patch is refused here, as an image's would be
        self.extractor  # the backbone loaded: weights of another architecture are refused here  # noqa: B018

    @property
    def extractor(self) -> DenseExtractor:
        if self._extractor is None:
            model, spec, identity = load_backbone(self.backbone, self.weights, self.device, self.cache_dir)
            self._weights_id = identity
            layer, facet = self.layer, self.facet
            if self.aggregation == "cls" and self.spec.cls == "final-norm":
                layer, facet = len(model.blocks) - 1, "token"  # CLS comes from the final norm
            self._extractor = DenseExtractor(model, spec, layer, facet, stride=self.stride,
                                             head_interleaved=self.spec.channels == "head-interleaved")
        return self._extractor

    def load(self, path: Path, resize: tuple[int, int] | None = None) -> torch.Tensor:
        """One image file -> the (3, H, W) tensor the backbone sees (runs in loader workers)."""
        return preprocess(path, self.spec, resize=parse_size(resize) or self.resize)

    def _batches(self, tensors):
        """(indices, batch tensor): runs of consecutive same-sized preprocessed images, at most
        batch_size each, in input order (so streams, e.g. vocabulary sampling, never depend on
        the batch size)."""
        group: list[tuple[int, torch.Tensor]] = []
        for i, x in enumerate(tensors):
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
                if self.spec.cls == "final-norm":
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

    def describe(self, images: Sequence) -> np.ndarray:
        out: np.ndarray | None = None
        for indices, batch in self._batches(loaded(self, images)):
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
        fitted = fit_vocabulary(self.iter_patch_features(database), self.clusters, budget=DEFAULT_BUDGET,
                                images=len(database), per_image=self.patches_per_image())
        self.centres = fitted.centres.float()
        self.fit_counts = {key: int(fitted.meta[key]) for key in SAMPLING_KEYS[2:]}

    def patches_per_image(self, resize=None) -> int | None:
        """Patch features each image gives at `resize` (else the method's): None where they depend on the
        image's own size (no resize), so a fit can be refused before any image is described."""
        size = parse_size(resize) or self.resize
        if self.spec.resize == "fixed":
            height, width = self.spec.input_size
        elif size is None:
            return None
        else:
            _, _, height, width = crop_offsets(*size, self.spec.patch)
        rows, columns = patch_grid(height, width, self.spec.patch, self.stride)
        return rows * columns

    def iter_patch_features(self, paths: Sequence[Path], resize=None):
        """Each image's (N, D) patch features as they enter VLAD, in input order.
        `resize` (H, W) overrides the method's resize (domain vocabularies use 320x320)."""
        for _, batch in self._batches(self.load(path, resize) for path in paths):
            yield from self.patch_features(batch).cpu()

    def fit_state(self) -> dict[str, np.ndarray]:
        fitted = self.needs_fit and self.centres is not None
        return {"centres": self.centres.cpu().numpy(), **counts_state(self.fit_counts)} if fitted else {}

    def load_fit_state(self, state: dict[str, np.ndarray]) -> None:
        # read from the cache: checked (as wide as the facet, as a named vocabulary is: `check_dim`)
        self.centres = torch.from_numpy(fitted_centres(state, self.clusters, self.spec.width, "anyloc"))
        self.fit_counts = counts_of_state(state)

    # ------------------------------------------------------------ PCA-whitening
    def postprocessor(self) -> PCAWhitening | None:
        """The -PCA presets: whitening fitted on the database descriptors (output L2-normalised)."""
        return PCAWhitening(self.pca_dim) if self.pca_dim else None

    def postprocess_datasets(self) -> list[str] | None:
        joint = pca_datasets(self.pca_on, self.dataset) if self.pca_dim else None
        return joint and joint[1]

