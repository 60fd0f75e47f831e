"""Where dense-vlad's words come from: its `vocabulary` option, as AnyLoc's.

    map            the evaluated database (fitted by the evaluation; transductive)
    DATASET        a benchmark's database under its default protocol, e.g. 17places
    DOMAIN         AnyLoc's domain datasets' databases with their strides, e.g. indoor
                   (distractor folders left out, as AnyLoc's vocabularies)
    FOLDER         every image under a folder of one's own
    FILE           a .npy / .pt file of (clusters, 128) centres (ours, or a bare array)

A vocabulary fitted here (dataset, domain, folder) is fitted once with the method's own
sampling and k-means and cached in `<cache>/vocabularies/dense-vlad/`, named by what it was
fitted on (protocol hashes or image contents) and the method's fit settings.
"""
from __future__ import annotations

import warnings

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError, closest_names
from ..hashing import canonical_hash
from ..paths import safe_name

#: RootSIFT's dimension: every bin size gives 128-dimensional descriptors of its own keypoints
SIFT_DIM = 128
VOCABULARY_FILE = "vocabulary.pt"
KINDS = ("map", "dataset", "domain", "folder", "file")


@dataclass(frozen=True)
class VocabularySource:
    kind: str  # one of KINDS
    option: str  # as given

    @property
    def path(self) -> Path:
        return Path(self.option).expanduser()

    def includes(self, dataset: str | None, info: dict) -> bool | None:
        """Whether the vocabulary was fitted on the evaluated dataset's database: by the datasets
        it was fitted on (None: a file that does not say; a folder is checked by image content
        when the record is made)."""
        if self.kind == "map":
            return True
        fitted = info.get("datasets")
        if fitted is None:
            return None if self.kind == "file" else False
        return dataset in fitted


def parse_vocabulary(option) -> VocabularySource:
    """The option checked, no data read: map, a path (file or folder), a benchmark or a domain."""
    from ..datasets import dataset_manifests
    from .anyloc_vocabulary import domain_names

    option = str(option) if isinstance(option, Path) else option
    if option == "map":
        return VocabularySource("map", option)
    path = Path(option).expanduser()
    if path.suffix in (".npy", ".pt") or "/" in option or option.startswith((".", "~")) or path.exists():
        if path.is_dir():
            return VocabularySource("folder", option)
        if not path.is_file():
            raise VPRBenchError(f"dense-vlad: vocabulary file {path} does not exist: check the path, or give map, a "
                                "dataset, a domain or a folder of images.")
        return VocabularySource("file", option)
    if option in dataset_manifests():
        return VocabularySource("dataset", option)
    if option in domain_names():
        return VocabularySource("domain", option)
    known = [*dataset_manifests(), *domain_names()]
    raise VPRBenchError(
        f"dense-vlad: option vocabulary takes map (the evaluated database), a dataset ({', '.join(list(dataset_manifests())[:3])}, "
        f"...), a domain ({', '.join(domain_names()[:3])}, ...), a folder of images or a .npy/.pt file of "
        f"(clusters, {SIFT_DIM}) centres; got {option!r}.{closest_names(option, known)}")


def _benchmark_protocol(name: str) -> str:
    from ..datasets import dataset_manifest, find_protocol

    return find_protocol(dataset_manifest(name), None).hash


def _fit_images(method, source: VocabularySource) -> tuple[dict, dict[str, int], list[Path]]:
    """(identity of the data, images per dataset or folder, the images in fitting order)."""
    from ..datasets import load_dataset
    from .anyloc_vocabulary import domain_datasets, vocabulary_images

    if source.kind == "folder":
        from ..datasets.identity import images_key
        from ..images import list_images

        images = list_images(source.path, recursive=True)
        if not images:
            raise VPRBenchError(f"dense-vlad: vocabulary folder {source.path} holds no images to fit on.")
        from ..datasets.identity import content_hashes

        digests = content_hashes(images, method.cache_dir)
        method.folder_digests = set(digests)
        return ({"images": images_key(images, source.path, digests=digests)}, {}, images)
    if source.kind == "dataset":
        pairs = [(source.option, 1)]
    else:
        pairs = domain_datasets(source.option)
    identity = {"datasets": [[name, stride, _benchmark_protocol(name)] for name, stride in pairs]}
    loaded, missing = {}, []
    for name, stride in pairs:
        try:
            loaded[name] = vocabulary_images(name, load_dataset(name, method.data_dir, fetch=False).database, stride)
        except VPRBenchError as error:
            missing.append(f"{name} ({error})")
    if missing:
        raise VPRBenchError(f"dense-vlad: cannot fit the {source.option!r} vocabulary: missing "
                            f"{'; '.join(missing)}. Get the data (`vprbench datasets`), or pass a vocabulary file.")
    return identity, {name: len(images) for name, images in loaded.items()}, [p for ps in loaded.values() for p in ps]


def check_centres(centres, clusters: int, where: str, meta: dict) -> np.ndarray:
    """(clusters, 128) float32 centres, or one line naming the file and what it was made for."""
    centres = np.asarray(centres, dtype=np.float32)
    if centres.shape[1] != SIFT_DIM:
        made_for = meta.get("method") or "/".join(str(meta[k]) for k in ("backbone", "layer", "facet") if k in meta)
        raise VPRBenchError(
            f"Vocabulary {where} has {centres.shape[1]}-dimensional centres{f' (made for {made_for})' if made_for else ''}, "
            f"but dense-vlad's RootSIFT descriptors are {SIFT_DIM}-dimensional: use a dense-vlad vocabulary "
            f"(map, a dataset, a domain, a folder of images) or a (clusters, {SIFT_DIM}) file.")
    if centres.shape[0] != clusters:
        raise VPRBenchError(f"Vocabulary {where} has {centres.shape[0]} clusters, the method asks for {clusters}.")
    return np.ascontiguousarray(centres)


def cached_vocabulary(method, source: VocabularySource) -> tuple[np.ndarray, dict]:
    """(centres, provenance) of a vocabulary that is not the evaluated database's."""
    from ..aggregation.vocabulary import Vocabulary, load_vocabulary, vocabularies_root

    if source.kind == "file":
        from .anyloc_provenance import released_provenance

        found = load_vocabulary(source.path)
        centres = check_centres(found.centres.numpy(), method.clusters, str(source.path), found.meta)
        file = released_provenance(found)  # {"source": "file" or "released", "sha256", ...}
        info = {**file, "fitted_on": found.meta.get("fitted_on") or f"unknown (file sha256:{file.get('sha256')})"}
        if "datasets" in found.meta:
            info["datasets"] = found.meta["datasets"]
        return centres, info
    identity, counts, images = _fit_images(method, source)
    key = _key(method.fit_recipe(), identity)
    path = vocabularies_root(method.cache_dir) / "dense-vlad" / f"{safe_name(source.path.name or source.option)}-{key}" / VOCABULARY_FILE
    fitted_on = (f"{len(images)} images in {source.path.resolve()} (content {identity['images'][:16]})"
                 if source.kind == "folder" else
                 ", ".join(f"the database of {name}:{protocol} ({counts[name]} images, every {stride})"
                           if stride > 1 else f"the database of {name} (protocol {protocol}, {counts[name]} images)"
                           for name, stride, protocol in identity["datasets"]))
    info = {"source": "fitted", "name": source.option, "fitted_on": fitted_on, "file": str(path), "images": len(images),
            **({"datasets": counts} if counts else {"folder": str(source.path.resolve())}), "data_identity": identity}
    found = _cached(path, method, key, said=False)  # said under the lock: another process may be fitting it now
    if found is None:
        from ..fsutil import lock, remove_stale, temporaries_of

        with lock(path.with_name(".fit.lock"), what=f"the dense-vlad vocabulary {source.option!r}"):
            found = _cached(path, method, key)  # another process may have fitted it while this one waited
            if found is None:
                import torch

                centres = method.fit_centres(images)
                Vocabulary(torch.from_numpy(centres), {**method.fit_recipe(), "source": source.option,
                                                      "fitted_on": fitted_on, "data": identity,
                                                      **({"datasets": counts} if counts else {})}).save(path)
                # every writer of `path` holds this lock: a temporary found now is a killed fit's (else kept for good)
                remove_stale(temporaries_of(path), age_s=0)
                found = load_vocabulary(path)
    return check_centres(found.centres.numpy(), method.clusters, str(path), found.meta), info


def _cached(path: Path, method, key: str, said: bool = True):
    """The vocabulary fitted earlier at `path`; None when there is none, or it is damaged, or it says it
    was fitted on other data or settings than its folder's `key` names (another entry's file copied or
    moved there: its centres would be recorded as fitted on this entry's data): it is the cache's own,
    fitted from data named in its key, so it is fitted again (and said so, when `said`: by the lock holder,
    which fits it; not by a process that then finds another's fit, nor twice by one)."""
    from ..aggregation.vocabulary import load_vocabulary

    if not path.is_file():
        return None
    try:
        found = load_vocabulary(path)
    except VPRBenchError as error:
        if said:
            warnings.warn(f"The cached dense-vlad vocabulary {path} is damaged or unreadable; fitting it again. "
                          f"(Why: {error})", stacklevel=2)
        return None
    if _key({k: found.meta.get(k) for k in method.fit_recipe()}, found.meta.get("data")) != key:
        if said:
            warnings.warn(f"The cached dense-vlad vocabulary {path} was fitted on other data or settings than its "
                          "folder names (another entry's file copied or moved there); fitting it again.", stacklevel=2)
        return None
    return found


def _key(recipe: dict, data) -> str:
    """The key of a vocabulary fitted as `recipe` says on `data` (their identity): its folder's name, and what
    the metadata in its file must give again."""
    return canonical_hash({"fit": recipe, "data": data})
