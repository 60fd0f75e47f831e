"""What a vocabulary's content says it is, whatever name it is found under: the authors' release
(known by its sha256), or the datasets and source a vprbench fit recorded; what a record names of it."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..aggregation.vocabulary import Vocabulary
from ..errors import VPRBenchError
from ..text import shortened
from .anyloc_vocabulary import (MAP_PREFIX, domain_names, is_released_setting, release, released_name, released_sources,
                                released_url, setting_words, source_datasets, vocabulary_policies)

#: the keys of a vprbench fit's metadata that say how its k-means saw the features
SAMPLING_KEYS = ("exact", "budget", "features_seen", "features_used")


def _released_folder(path) -> tuple[str, str | None]:
    """(the file's sha256, the authors' released folder whose bytes it is, else None)."""
    from ..weights import file_sha256

    digest = file_sha256(path)
    return digest, next((folder for folder, known in release()["sha256"].items() if known == digest), None)


def released_provenance(vocabulary: Vocabulary) -> dict:
    """{"source": "released", repository, commit, url, sha256} when the file is a released one, else the file's sha256."""
    path = vocabulary.meta.get("path") or vocabulary.meta.get("imported_from")
    if not path or not Path(path).is_file():
        return {}
    digest, folder = _released_folder(path)
    source = next((s for s in released_sources() if released_name(s) == folder), None) if folder else None
    if source is None:
        return {"source": "file", "sha256": digest, "file": str(path)}
    r = release()
    return {"source": "released", "released_as": folder, "repository": r["repository"], "commit": r["commit"],
            "url": released_url(source), "sha256": digest, "file": str(path), "datasets": source_datasets(source)}


def released_as(vocabulary: Vocabulary) -> str | None:
    """The released folder whose bytes the file is, or the file it was imported from ('indoor'); None otherwise.
    An import re-saved under other metadata keeps the original's path: its content is still the release's."""
    for key in ("path", "imported_from"):
        path = vocabulary.meta.get(key)
        if isinstance(path, str) and Path(path).is_file() and (folder := _released_folder(path)[1]):
            return folder
    return None


def check_released_setting(vocabulary: Vocabulary, backbone: str, layer: int, facet: str,
                           stride: int | None = None) -> None:
    """The authors' released centres serve the features they were fitted on only (ViT-G/14 block 31 value with
    the official weights): a bare tensor names no setting, so its sha256 says it, whatever a path or import claims.
    A checkpoint file of one's own (BACKBONE@<hex>) may be the official one (DINOv2 publishes no sha256): taken on
    the user's word; random weights never are."""
    from ..features.backbones import RANDOM

    folder = released_as(vocabulary)
    name, _, weights = backbone.partition("@")
    if folder is None or weights != RANDOM and is_released_setting(name, layer, facet, vocabulary.clusters, stride):
        return
    r = release()
    path = vocabulary.meta.get("imported_from") or vocabulary.meta.get("path")
    raise VPRBenchError(
        f"Vocabulary {path} is the authors' released {folder!r} centres, fitted on "
        f"{setting_words(r['backbone'], int(r['layer']), r['facet'], int(r['clusters']))} (official weights), but these "
        f"features are {setting_words(backbone, layer, facet, vocabulary.clusters, stride)}: use them with "
        f"--backbone {r['backbone']} --layer {r['layer']} --facet {r['facet']}, or fit a vocabulary for these "
        "features (`vprbench vocabulary fit`).")


def file_provenance(vocabulary: Vocabulary) -> dict:
    """Where the centres came from, and what they were fitted on: the datasets whose databases a vprbench fit
    records (the authors' release is known by its name) and, for a folder of one's own's, its path."""
    found = released_provenance(vocabulary)
    meta = vocabulary.meta
    if found.get("source") == "file" and "vocabularies" in Path(found["file"]).parts:
        found["source"] = "cache"  # fitted earlier with `vprbench vocabulary fit` or imported
    fitted = meta.get("datasets")
    if isinstance(fitted, (dict, list)) and fitted and all(isinstance(name, str) for name in fitted):
        found["datasets"] = list(fitted)
    if isinstance(meta.get("folder"), str):  # named by its content too: the name alone may be another folder's
        named = f" ({recorded(meta['source'])})" if isinstance(meta.get("source"), str) else ""
        folder = recorded(meta["folder"])
        found.update(folder=folder, fitted_on=f"the database of the folder {folder}{named}")
    if found.get("source") in ("cache", "file") and ("imported_from" in meta or "features_seen" in meta):
        found["made_by"] = "imported" if "imported_from" in meta else "fitted"
    found.update(fit_sampling(meta))
    # the features' settings the key leaves out: the record tells what the centres were fitted at
    found.update({f"fitted_{key}": recorded(meta[key]) for key in ("stride", "resize", "image_size") if key in meta})
    return found


def recorded(value):
    """A file's metadata value as a record keeps it: a fit's (number, size, path) as it is, else its text, cut."""
    if isinstance(value, int) or isinstance(value, list) and len(value) <= 2 and all(type(v) is int for v in value):
        return value
    return shortened(value, 1000)


def content_source(vocabulary: Vocabulary, name: str) -> str | None:
    """The source the centres' content names when `name` claims another (a domain, map-DATASET): what a
    vprbench fit records, or the authors' release known by its sha256. None: no conflict (or a name of one's own)."""
    if name not in domain_names() and not name.startswith(MAP_PREFIX):
        return None
    own = vocabulary.meta.get("source")
    if not isinstance(own, str) or own not in domain_names() and not own.startswith(MAP_PREFIX):
        release_folder = released_provenance(vocabulary).get("released_as")
        own = next((s for s, folder in vocabulary_policies()["released"].items() if folder == release_folder), None)
    return own if own not in (None, name) else None


def fit_sampling(meta: dict) -> dict:
    """{"sampling": {exact, budget, features_seen, features_used}} of a vprbench fit (the paper's k-means sees
    every patch: exact; vprbench's default keeps a seeded sample of at most `budget`), {} where a file says none."""
    if "exact" not in meta:
        return {}
    return {"sampling": {key: recorded(meta[key]) for key in SAMPLING_KEYS if key in meta}}


def release_status(name: str, vocabulary: Vocabulary, backbone: str, layer: int, facet: str, clusters: int,
                   stride: int | None = None) -> dict:
    """For a name the authors released centres under, at their setting: {"authors_release": whether these centres
    are that release, by sha256}; centres fitted or imported under the name never pass for the paper's. {} else."""
    if released_name(name) is None or not is_released_setting(backbone, layer, facet, clusters, stride):
        return {}
    return {"authors_release": released_provenance(vocabulary).get("source") == "released"}


def counts_state(counts: dict) -> dict:
    """A run's fit's features seen and used as its fit state keeps them beside the centres (read back with them)."""
    return {"features": np.array([counts[key] for key in SAMPLING_KEYS[2:]], np.int64)} if counts else {}


def counts_of_state(state: dict) -> dict:
    """The features seen and used a fit state keeps ({} for one saved before it kept them, or not two whole numbers)."""
    counts = np.asarray(state.get("features", []))
    return dict(zip(SAMPLING_KEYS[2:], map(int, counts))) if counts.shape == (2,) and counts.dtype.kind in "iu" else {}
