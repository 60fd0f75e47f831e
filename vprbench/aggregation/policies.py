"""Which images a VLAD vocabulary is fitted on: map-specific and AnyLoc's domain vocabularies.

Domain membership is data (manifests/vocabularies.toml). Fitting takes a feature
extractor from the caller, so this module knows nothing about backbones:

    extract(paths: list[Path]) -> iterable of (N, D) patch features, one per path, in order

For domain vocabularies the extractor must resize images to `domain_image_size()`
(320 x 320, as the authors' script); map-specific ones use the dataset's own preprocessing.
"""
from __future__ import annotations

import tomllib
from functools import cache
from importlib.resources import files
from pathlib import Path
from typing import Callable, Iterable, Sequence

from ..errors import VPRBenchError, closest_names
from .vocabulary import (
    DEFAULT_BUDGET, KMEANS_SEED, RELEASED_FILE, VOCABULARY_FILE, Vocabulary, fit_vocabulary, load_vocabulary,
    vocabulary_dir,
)

Extractor = Callable[[Sequence[Path]], Iterable]
MAP_PREFIX = "map-"


@cache
def vocabulary_policies() -> dict:
    return tomllib.loads((files("vprbench.manifests") / "vocabularies.toml").read_text())


def domain_names() -> list[str]:
    policies = vocabulary_policies()
    return [*policies["domains"], *policies["groups"]]


def domain_image_size() -> tuple[int, int]:
    height, width = vocabulary_policies()["image_size"]
    return int(height), int(width)


def domain_datasets(domain: str) -> list[tuple[str, int]]:
    """(dataset name, database stride) pairs of a domain or a group of domains, in fitting order."""
    policies = vocabulary_policies()
    if domain in policies["domains"]:
        pairs = [(name, int(stride)) for name, stride in policies["domains"][domain]]
    elif domain in policies["groups"]:
        pairs = [pair for member in policies["groups"][domain] for pair in domain_datasets(member)]
    else:
        raise VPRBenchError(f"Unknown vocabulary domain {domain!r}; known: {', '.join(domain_names())}."
                        + closest_names(domain, domain_names()))
    order = policies["order"]
    return sorted(pairs, key=lambda pair: order.index(pair[0]))


def map_stride(dataset: str) -> int:
    return int(vocabulary_policies()["map_stride"].get(dataset, 1))


def paper_vocabulary(dataset: str) -> str:
    """The source the paper's AnyLoc-VLAD-DINOv2 uses for `dataset`: a domain, or `map-<dataset>`."""
    choice = vocabulary_policies()["paper_vocabulary"].get(dataset, "map")
    return f"{MAP_PREFIX}{dataset}" if choice == "map" else choice


def released_name(source: str) -> str | None:
    """Folder name of the authors' released centres for a vprbench source name, if they released one."""
    return vocabulary_policies()["released"].get(source)


def _load_all(pairs: list[tuple[str, int]], data_dir) -> list[tuple[str, list[Path]]]:
    """Database images of every dataset, strided; one error naming every dataset that is missing."""
    from ..datasets import load_dataset

    loaded, missing = [], []
    for name, stride in pairs:
        try:
            dataset = load_dataset(name, data_dir, fetch=False)
        except VPRBenchError as exc:
            missing.append(f"  - {name}: {exc}")
            continue
        loaded.append((name, list(dataset.database)[::stride]))
    if missing:
        raise VPRBenchError(
            "Cannot fit this vocabulary: these datasets are needed and could not be loaded:\n"
            + "\n".join(missing)
            + "\nGet them (see `vprbench datasets`), or use the authors' released centres instead: "
            "pass the path of their c_centers.pt as the vocabulary."
        )
    return loaded


def fit_domain_vocabulary(
    domain: str, extract: Extractor, clusters: int, *, data_dir=None, exact: bool = False,
    budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED, meta: dict | None = None,
) -> Vocabulary:
    """Fit AnyLoc's vocabulary of a domain (indoor, urban, aerial, ..., structured, global).

    `extract` must produce features of images resized to `domain_image_size()`.
    """
    loaded = _load_all(domain_datasets(domain), data_dir)
    paths = [path for _, images in loaded for path in images]
    sources = {name: len(images) for name, images in loaded}
    info = {**(meta or {}), "source": domain, "datasets": sources, "image_size": list(domain_image_size())}
    return fit_vocabulary(extract(paths), clusters, exact=exact, budget=budget, seed=seed, meta=info)


def fit_map_vocabulary(
    dataset: str, extract: Extractor, clusters: int, *, data_dir=None, exact: bool = False,
    budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED, meta: dict | None = None,
) -> Vocabulary:
    """Fit a map-specific vocabulary on the dataset's own database images."""
    (name, images), = _load_all([(dataset, map_stride(dataset))], data_dir)
    info = {**(meta or {}), "source": f"{MAP_PREFIX}{name}", "datasets": {name: len(images)}}
    return fit_vocabulary(extract(images), clusters, exact=exact, budget=budget, seed=seed, meta=info)


def fit_database_vocabulary(
    paths: Sequence[Path], extract: Extractor, clusters: int, *, exact: bool = False,
    budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED, meta: dict | None = None,
) -> Vocabulary:
    """Map-specific vocabulary from database paths already at hand (e.g. `Method.fit(database)`)."""
    info = {**(meta or {}), "images": len(paths)}
    return fit_vocabulary(extract(list(paths)), clusters, exact=exact, budget=budget, seed=seed, meta=info)


def find_vocabulary(source: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None) -> Vocabulary | None:
    """A cached vocabulary for these feature settings and source, or None.

    Looks in the cache folder for our vocabulary.pt, then for the authors' c_centers.pt
    under the source name or the authors' folder name (so their released folders can be
    copied into the cache as they are).
    """
    folders = [vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir)]
    released = released_name(source)
    if released:
        folders.append(folders[0].parent / released)
    for folder in folders:
        for name in (VOCABULARY_FILE, RELEASED_FILE):
            if (folder / name).is_file():
                return load_vocabulary(folder / name)
    return None


def save_to_cache(vocabulary: Vocabulary, backbone: str, layer: int, facet: str, source: str, cache_dir=None) -> Path:
    meta = {**vocabulary.meta, "backbone": backbone, "layer": layer, "facet": facet, "source": source}
    vocabulary.meta = meta
    folder = vocabulary_dir(backbone, layer, facet, vocabulary.clusters, source, cache_dir)
    return vocabulary.save(folder / VOCABULARY_FILE)


def resolve_vocabulary(spec: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None) -> Vocabulary:
    """The `vocabulary` option: a file or folder path, or a cached source name
    (a domain, or map-<dataset>). Raises a clear error saying how to create it."""
    path = Path(spec).expanduser()
    if path.suffix in (".pt", ".npy") or "/" in spec or path.exists():
        vocabulary = load_vocabulary(path)
    else:
        vocabulary = find_vocabulary(spec, backbone, layer, facet, clusters, cache_dir)
        if vocabulary is None:
            where = vocabulary_dir(backbone, layer, facet, clusters, spec, cache_dir)
            how = f"--dataset {spec[len(MAP_PREFIX):]}" if spec.startswith(MAP_PREFIX) else f"--domain {spec}"
            raise VPRBenchError(
                f"No {spec!r} vocabulary for {backbone} layer {layer} {facet} with {clusters} clusters "
                f"(looked in {where}). Fit it with `vprbench vocabulary fit {how} ...`, or pass "
                "the path of the authors' released c_centers.pt as the vocabulary."
            )
    if vocabulary.clusters != clusters:
        raise VPRBenchError(
            f"Vocabulary {vocabulary.meta.get('path', spec)} has {vocabulary.clusters} clusters, "
            f"the method asks for {clusters}."
        )
    return vocabulary
