"""VLAD vocabularies: the fitted centres, their file and cache key, and the fit.

`fit_vocabulary` is AnyLoc's fit (`vprbench.aggregation.kmeans`): k-means on every patch
feature (`exact=True`, as the official code) or on a bounded random sample of them.
"""
from __future__ import annotations

import io
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import VPRBenchError
from ..fsutil import atomic_write
from ..paths import cache_root, portable_name, regular_file
from ..text import shortened
from ..weights import read_torch_file
from .kmeans import DEFAULT_BUDGET, KMEANS_SEED, FeatureSampler, kmeans_cosine

#: a damaged vocabulary file's remedy (the authors' released centres are checked by their sha256 at
#: every use and downloaded again: a damaged one is never read)
FIT_AGAIN = "a copy that stopped early leaves such a file: copy it again, or fit it again (`vprbench vocabulary fit`)."
#: file name of the authors' released centres (a bare (K, D) float tensor)
RELEASED_FILE = "c_centers.pt"
VOCABULARY_FILE = "vocabulary.pt"


@dataclass
class Vocabulary:
    """VLAD cluster centres (K, D) and what produced them."""

    centres: torch.Tensor
    meta: dict = field(default_factory=dict)

    @property
    def clusters(self) -> int:
        return int(self.centres.shape[0])

    @property
    def dim(self) -> int:
        return int(self.centres.shape[1])

    def check_dim(self, feature_dim: int) -> None:
        if feature_dim != self.dim:
            source = self.meta.get("path") or self.meta.get("source") or "the vocabulary"
            fitted = self.meta.get("method") or "/".join(str(self.meta[k]) for k in ("backbone", "layer", "facet")
                                                          if k in self.meta)
            raise VPRBenchError(
                f"Vocabulary {source} has {self.dim}-dimensional centres but the features are "
                f"{feature_dim}-dimensional: it was fitted for other features (another backbone, layer or facet"
                f"{f': {fitted}' if fitted else ''}). Use a vocabulary fitted for these features."
            )

    def check_setting(self, backbone: str, layer: int, facet: str, stride: int | None = None) -> None:
        """Refuse centres whose metadata names other features (a bare released tensor names none).
        `stride` None: the backbone's own."""
        asked = {"backbone": backbone, "layer": layer, "facet": facet,
                 "stride": default_stride(backbone) if stride is None else stride}
        made = {key: self.meta[key] for key in asked if self.meta.get(key) is not None and asked[key] is not None}
        if any(str(value) != str(asked[key]) for key, value in made.items()):
            source = self.meta.get("path") or self.meta.get("imported_from") or self.meta.get("source") or "the vocabulary"
            named = [key for key in made if key != "stride" or str(made[key]) != str(asked[key])]  # a stride if it differs
            shown = " ".join(f"{key} {shortened(made[key])}" for key in named)  # a hand-made file's may be huge
            wanted = " ".join(f"{key} {asked[key]}" for key in asked if key != "stride" or key in named)
            raise VPRBenchError(
                f"Vocabulary {source} was fitted on {shown}, but these features are {wanted}: use a vocabulary "
                "fitted on them (`vprbench vocabulary fit`).")

    def save(self, path: str | Path) -> Path:
        """Written whole or not at all (a process killed while writing, or a full disk, leaves the
        file as it was): a cached vocabulary is read by other runs."""
        path = Path(path)
        centres = self.centres.float().cpu().contiguous()
        buffer = io.BytesIO()  # torch.save's own writes fail on a full disk with a RuntimeError, no OSError
        torch.save({"centres": centres, "meta": dict(self.meta), "crc32": centres_checksum(centres)}, buffer)
        # a fit killed while saving left its temporary (never read): atomic_write removes this file's own once
        # an hour old (--output may be any folder, holding other programs' .*.tmp files)
        atomic_write(path, buffer.getvalue())
        return path


def centres_checksum(centres: torch.Tensor) -> int:
    """crc32 of the centres' float32 bytes (little-endian): a saved vocabulary is checked on load
    (torch.load does not check the bytes it reads)."""
    return zlib.crc32(np.ascontiguousarray(centres.float().cpu().numpy(), dtype="<f4").tobytes())


def vocabulary_file_in(folder: Path) -> Path | None:
    """The file a vocabulary folder is read from: ours (`vocabulary.pt`), else the authors' `c_centers.pt`."""
    return next((folder / name for name in (VOCABULARY_FILE, RELEASED_FILE) if (folder / name).is_file()), None)


def load_vocabulary(path: str | Path) -> Vocabulary:
    """A vocabulary file: ours (`vocabulary.pt`) or the authors' released `c_centers.pt`
    (a bare tensor); a folder holding either file is accepted too."""
    path = Path(path).expanduser()
    if path.is_dir():
        held = vocabulary_file_in(path)
        if held is None:
            raise VPRBenchError(f"Folder {path} holds neither {VOCABULARY_FILE} nor {RELEASED_FILE}.")
        path = held
    if not regular_file(path, "Vocabulary file"):
        raise VPRBenchError(f"Vocabulary file {path} does not exist: check the path (a .pt or .npy file of centres, "
                            f"or a folder holding {VOCABULARY_FILE} or {RELEASED_FILE}).")
    if path.suffix == ".npy":
        from ..datasets.layouts.npy import read_npy

        # the one .npy reader of files from elsewhere: no pickle run, no size its header claims allocated
        # beyond the file's bytes
        data = read_npy(path, "vocabulary file", "a (clusters, dim) float array")
    else:
        data = read_torch_file(path, "vocabulary file", remedy=FIT_AGAIN)
    meta, written = {}, None
    if isinstance(data, dict):
        if "centres" not in data:
            raise VPRBenchError(f"Vocabulary file {path} has no 'centres' entry (keys: {sorted(map(str, data))}).")
        data, meta, written = data["centres"], data.get("meta", {}), data.get("crc32")
        if not isinstance(meta, dict) or not all(isinstance(key, str) for key in meta):
            raise VPRBenchError(f"Vocabulary file {path} has a 'meta' entry that is no table of named values "
                                f"({type(meta).__name__}): it was not written by vprbench; fit it again (`vprbench vocabulary fit`).")
        meta = dict(meta)
    try:
        raw = torch.as_tensor(np.asarray(data) if isinstance(data, np.ndarray) else data)
    except (TypeError, ValueError, RuntimeError):
        raise VPRBenchError(f"Vocabulary file {path} holds a {type(data).__name__}, not a (clusters, dim) array of numbers.") from None
    if not raw.is_floating_point():  # centres are means: whole numbers, truth values or complex ones are no centres
        raise VPRBenchError(f"Vocabulary file {path} holds {str(raw.dtype).removeprefix('torch.')} values, expected "
                            "floating-point centres (float32): check the file (its centres were saved as another type).")
    centres = raw.float()
    if centres.dim() != 2 or centres.shape[0] < 1:
        raise VPRBenchError(f"Vocabulary file {path} holds a tensor of shape {tuple(centres.shape)}, expected (clusters, dim).")
    # None: a bare array, or saved before vocabularies carried a checksum: the zip's own CRC-32s check those
    if written is None:
        _check_zip_crcs(path)
    elif type(written) is not int or written != centres_checksum(centres):
        raise VPRBenchError(f"Vocabulary file {path} is damaged: its centres no longer match the checksum written with "
                            "them. Delete it and fit it again (`vprbench vocabulary fit`).")
    bad = (~torch.isfinite(centres)).nonzero()
    if len(bad):  # after the checks: a damaged file is named as damaged
        cluster, column = map(int, bad[0])
        raise VPRBenchError(f"Vocabulary file {path} has {len(bad)} NaN or infinite value(s) in its centres (first "
                            f"{float(centres[cluster, column])} at cluster {cluster}, dim {column}), expected finite "
                            "numbers: fit it again (`vprbench vocabulary fit`).")
    if str(meta.setdefault("clusters", int(centres.shape[0]))) != str(centres.shape[0]):  # shown and imported as said
        raise VPRBenchError(f"Vocabulary file {path} says it has {shortened(meta['clusters'])} clusters but holds "
                            f"{centres.shape[0]} centres (edited by hand?): fit it again (`vprbench vocabulary fit`).")
    meta["path"] = str(path)
    return Vocabulary(centres, meta)


def _check_zip_crcs(path: Path) -> None:
    """A PyTorch zip file's entries against the CRC-32 its writer stored with each (torch.load reads
    without checking them): a file without our checksum (the authors' release, or saved before
    vocabularies carried one) is checked, not trusted as it is. Entries written without a CRC (torch's
    CRC option off: 0) and the pre-zip format carry nothing to check."""
    if path.suffix == ".npy" or not zipfile.is_zipfile(path):
        return
    try:
        with zipfile.ZipFile(path) as archive:
            for entry in archive.infolist():
                if entry.CRC or not entry.file_size:
                    with archive.open(entry) as stream:
                        while stream.read(1 << 20):
                            pass
    except (zipfile.BadZipFile, EOFError) as error:
        raise VPRBenchError(f"Vocabulary file {path} is damaged: its bytes no longer match the CRC-32 written with "
                            f"them ({error}). Delete it and fit, import or download it again (`vprbench vocabulary "
                            "fit`, `import`, or `download` for the authors' released centres).") from None


def catalogued(backbone: str):
    """The catalogue's entry of `backbone` (BACKBONE or BACKBONE@weights, a vocabulary key's name), or None
    for a name it does not know."""
    from ..features.catalogue import backbone_spec

    try:
        return backbone_spec(backbone.partition("@")[0])
    except VPRBenchError:
        return None


def default_stride(backbone: str) -> int | None:
    """The patch stride `backbone` runs at unless told: the catalogue's (DINO v1: 4), else its patch;
    None for a name the catalogue does not know."""
    entry = catalogued(backbone)
    return entry.default_stride if entry is not None else None


def at_default_stride(backbone: str, stride: int | None) -> bool:
    """Whether `stride` (None: unset) is the backbone's own, which vocabulary keys leave unsaid."""
    return stride is None or int(stride) == default_stride(backbone)


def feature_variant(backbone: str) -> dict[str, str]:
    """The catalogue's `feature_variant` of `backbone` (what else changes its features, as the store key
    takes it: DINOv3's bfloat16 RoPE periods), {} for a name it does not know."""
    entry = catalogued(backbone)
    return entry.feature_variant if entry is not None else {}


def vocabulary_key(backbone: str, layer: int, facet: str, clusters: int, stride: int | None = None) -> str:
    """Folder name of a feature setting, as the authors' release: `dinov2_vitg14-l31-value-c32`.

    `backbone` carries the weights (BACKBONE@random, BACKBONE@<sha256 prefix>); a patch stride other
    than the backbone's own (DINO v1 at 8, not 4) adds `-s<stride>`: other features, other centres.
    None: the backbone's own stride. The backbone's `feature_variant` adds `-<name>-<value>` each
    (`-rope_periods-bfloat16`), as it enters the store key. Names are kept portable (`portable_name`)."""
    key = f"{backbone}-l{layer}-{facet}-c{clusters}"
    if not at_default_stride(backbone, stride):
        key += f"-s{int(stride)}"
    key += "".join(f"-{name}-{value}" for name, value in sorted(feature_variant(backbone).items()))
    return portable_name(key)


def vocabulary_dir(backbone: str, layer: int, facet: str, clusters: int, source: str, cache_dir=None,
                   stride: int | None = None) -> Path:
    """cache_root()/vocabularies/<backbone>-l<layer>-<facet>-c<clusters>[-s<stride>]/<source>/.

    `source` is a domain name (indoor, urban, ...) or `map-<dataset>` for a map-specific
    vocabulary. The authors' released folders (with c_centers.pt) can be copied here under
    their own names: they are found too (see vprbench.methods.anyloc_vocabulary)."""
    return vocabularies_root(cache_dir) / vocabulary_key(backbone, layer, facet, clusters, stride) / portable_name(source)


def legacy_vocabulary_dir(backbone: str, layer: int, facet: str, clusters: int, source: str, cache_dir=None,
                          stride: int | None = None) -> Path | None:
    """Where vprbench kept this vocabulary before folder names were made portable (a timm:ARCH
    backbone's ':' as it is), when that differs and names one folder; read, never written."""
    if not at_default_stride(backbone, stride) or feature_variant(backbone):
        return None  # neither was keyed then: no old folder holds these features' centres
    key, found = f"{backbone}-l{layer}-{facet}-c{clusters}", vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir)
    if any(sep in part for part in (key, source) for sep in "/\\") or (key, source) == (found.parent.name, found.name):
        return None
    return vocabularies_root(cache_dir) / key / source


def vocabularies_root(cache_dir=None) -> Path:
    """The cache folder every vocabulary lies under (one folder per setting, then per source)."""
    return cache_root(cache_dir) / "vocabularies"


def fit_vocabulary(
    features: Iterable, clusters: int, *, exact: bool = False, budget: int = DEFAULT_BUDGET,
    seed: int = KMEANS_SEED, meta: dict | None = None, progress=None, images: int | None = None,
    per_image: int | None = None,
) -> Vocabulary:
    """Fit a vocabulary on a stream of per-image (N, D) patch features.

    exact=True: AnyLoc's fit, k-means on every feature (memory grows with the dataset).
    exact=False: k-means on a seeded reservoir sample of at most `budget` features.
    `progress` (vprbench.progress) shows the k-means as a phase. `images` and `per_image` (the stream's
    length and features per image, where the resize fixes them) refuse too many clusters before it is read.
    """
    from ..progress import phase

    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**32:  # numpy's seed range
        raise VPRBenchError(f"The vocabulary's seed (--seed) must be a whole number >= 0, got {seed!r}; "
                            f"the largest is {2**32 - 1}.")
    # before the stream is read (describing the images is most of a fit); k-means checks it again
    if not exact and clusters > budget:
        raise VPRBenchError(f"Cannot fit {clusters} clusters on a sample of at most {budget:,} features (the budget): "
                            f"give fewer clusters or a budget of at least {clusters}.")
    if images is not None and per_image is not None and clusters > images * per_image:
        raise VPRBenchError(f"Cannot fit {clusters} clusters on {images * per_image:,} features ({images:,} images x "
                            f"{per_image:,} patches each at this input size): give at most {images * per_image} clusters, "
                            "or fit on more images.")  # a larger resize gives more only where the backbone takes it
    if exact:
        chunks = [torch.as_tensor(f).float().reshape(-1, torch.as_tensor(f).shape[-1]) for f in features]
        if not chunks:
            raise VPRBenchError("No features were given to fit the vocabulary (no images?).")
        sample = F.normalize(torch.cat(chunks), dim=-1)
        seen = len(sample)
    else:
        sampler = FeatureSampler(budget, seed)
        for f in features:
            sampler.add(f)
        sample, seen = torch.from_numpy(sampler.sample()), sampler.seen
    label = " ".join(filter(None, ("vocabulary", (meta or {}).get("source"))))
    with phase(progress, f"{label} k-means ({clusters} clusters, {len(sample):,} features)"):
        centres, iterations = kmeans_cosine(sample, clusters, seed=seed)
    info = {"clusters": clusters, "seed": seed, "exact": exact, "features_seen": int(seen),
            "features_used": int(len(sample)), "iterations": iterations}
    if not exact:
        info["budget"] = budget
    return Vocabulary(centres, {**(meta or {}), **info})

