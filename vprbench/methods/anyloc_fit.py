"""Fitting AnyLoc's vocabularies on datasets: a domain's (its datasets' databases) or a map-specific one
(one dataset's database). Fitting takes a feature extractor from the caller, so this module knows
nothing about backbones:

    extract(paths: list[Path]) -> iterable of (N, D) patch features, one per path, in order

For domain vocabularies the extractor must resize images to `domain_image_size()`
(320 x 320, as the authors' script); map-specific ones use the dataset's own preprocessing.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable, Iterable, Iterator, Sequence

from ..aggregation.kmeans import DEFAULT_BUDGET, KMEANS_SEED
from ..aggregation.vocabulary import Vocabulary, fit_vocabulary
from ..errors import ProblemList, VPRBenchError
from ..text import one_line
from .anyloc_vocabulary import (MAP_PREFIX, OWN_CONTENT_DIGITS, domain_datasets, domain_image_size, map_stride,
                                vocabulary_images)

Extractor = Callable[[Sequence[Path]], Iterable]


def _load_all(pairs: list[tuple[str, int]], data_dir, cache_dir=None) -> list[tuple[object, list[Path]]]:
    """(dataset, its database images strided) of every dataset; one error naming every dataset that is missing.
    `cache_dir` memoises the hashes of a folder of one's own's images (its identity)."""
    from ..datasets import load_dataset

    loaded, missing = [], []
    for name, stride in pairs:
        try:
            dataset = load_dataset(name, data_dir, fetch=False, cache_dir=cache_dir)
        except VPRBenchError as exc:
            missing.append(f"  - {one_line(name)}: {one_line(exc)}")
            continue
        loaded.append((dataset, vocabulary_images(name, dataset.database, stride)))
    if missing:
        raise ProblemList(
            "Cannot fit this vocabulary: these datasets are needed and could not be loaded:\n"
            + "\n".join(missing)
            + "\nGet them (see `vprbench datasets`), or use the authors' released centres instead: "
            "pass the path of their c_centers.pt as the vocabulary."
        )
    return loaded


def fit_domain_vocabulary(
    domain: str, extract: Extractor, clusters: int, *, data_dir=None, exact: bool = False,
    budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED, meta: dict | None = None, progress=None,
    per_image: int | None = None, cache_dir=None,
) -> Vocabulary:
    """Fit AnyLoc's vocabulary of a domain (indoor, urban, aerial, ..., structured, global).

    `extract` must produce features of images resized to `domain_image_size()`; `progress`
    (vprbench.progress) counts the images described, then shows the k-means. `per_image`: the
    features each image gives, when known (too many clusters are refused before any is described);
    `cache_dir`: the cache the images' hashes are memoised in.
    """
    loaded = _load_all(domain_datasets(domain), data_dir, cache_dir)
    paths = [path for _, images in loaded for path in images]
    sources = {dataset.name: len(images) for dataset, images in loaded}
    info = {**(meta or {}), "source": domain, "datasets": sources, "image_size": list(domain_image_size())}
    return fit_vocabulary(_counted(extract(paths), len(paths), domain, progress), clusters, exact=exact,
                          budget=budget, seed=seed, meta=info, progress=progress, images=len(paths),
                          per_image=per_image)


def packed_digests(digests) -> bytes:
    """Images' sha256 (hex) as a vocabulary's metadata keeps them: 32 bytes each, sorted, one bytes object, so
    a fit on a Pitts-250k-size folder adds 12 MB loaded in 0.05 s (as 254,064 strings: 19 MB, 0.9 s)."""
    return b"".join(sorted({bytes.fromhex(d) for d in digests}))


def recorded_image_digests(vocabulary: Vocabulary) -> set[str]:
    """sha256 (hex) of each image a folder of one's own's map vocabulary was fitted on, as its fit recorded
    them (empty where it did not)."""
    packed = vocabulary.meta.get("image_digests")
    if not isinstance(packed, bytes) or len(packed) % 32:
        return set()
    return {packed[i:i + 32].hex() for i in range(0, len(packed), 32)}


def fit_map_vocabulary(
    dataset: str, extract: Extractor, clusters: int, *, data_dir=None, exact: bool = False,
    budget: int = DEFAULT_BUDGET, seed: int = KMEANS_SEED, meta: dict | None = None, progress=None,
    per_image: int | None = None, cache_dir=None,
) -> Vocabulary:
    """Fit a map-specific vocabulary on the dataset's own database images (distractors left out);
    `progress` and `per_image` as for `fit_domain_vocabulary`; `cache_dir` memoises the images' hashes."""
    (loaded, images), = _load_all([(dataset, map_stride(dataset))], data_dir, cache_dir)
    own = {}
    if loaded.kind == "own":  # its images by content: a run on another folder of its name is not fitted on them
        digest_of = dict(zip(loaded.database, loaded.image_digests(cache_dir)["database"]))
        own = {"folder": str(loaded.root.resolve()), "image_digests": packed_digests(digest_of[p] for p in images)}
    info = {**(meta or {}), "source": map_source(loaded, cache_dir), "datasets": {loaded.name: len(images)}, **own}
    return fit_vocabulary(_counted(extract(images), len(images), info["source"], progress), clusters, exact=exact,
                          budget=budget, seed=seed, meta=info, progress=progress, images=len(images),
                          per_image=per_image)


def map_source(dataset, cache_dir=None) -> str:
    """The source name of a dataset's map-specific vocabulary: map-<its name> (not the path given: a folder's
    './mydata' would key its centres by that path); a folder of one's own's also by its database's content,
    as two folders may share a name (the authors' released centres are found by a benchmark's plain name)."""
    if dataset.kind != "own":
        return f"{MAP_PREFIX}{dataset.name}"
    return f"{MAP_PREFIX}{dataset.name}-{dataset.images_fingerprint(cache_dir)['database'][:OWN_CONTENT_DIGITS]}"


def _counted(features: Iterable, total: int, source: str, progress) -> Iterator:
    """`features`, one image's at a time, counted as images described (describing is most of a fit)."""
    from ..progress import Silent

    progress = progress or Silent()
    task = progress.add_task(f"vocabulary {source} images", total=total)
    for found in features:
        yield found
        progress.advance(task)
