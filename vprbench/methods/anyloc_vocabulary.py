"""AnyLoc's vocabulary policy: which images a VLAD vocabulary is fitted on (map-specific
and domain vocabularies), the authors' released centres, and the `vocabulary` option.

Domain membership is data (manifests/vocabularies.toml); fitting is anyloc_fit.py; what a file's
content says it is (the release by sha256, a fit's metadata) is anyloc_provenance.py.
"""
from __future__ import annotations

import glob
import tomllib
from functools import cache
from importlib.resources import files
from pathlib import Path
from typing import Sequence

from ..aggregation.vocabulary import (
    RELEASED_FILE, VOCABULARY_FILE, Vocabulary, at_default_stride, catalogued, default_stride, legacy_vocabulary_dir,
    load_vocabulary, vocabulary_dir, vocabulary_file_in,
)
from ..errors import VPRBenchError, closest_names, network_reason
from ..fsutil import lock, remove_stale, write_in_turn

MAP_PREFIX = "map-"
#: hex digits of a folder of one's own's database content in its map vocabulary's name
OWN_CONTENT_DIGITS = 12


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


def vocabulary_images(dataset: str, database: Sequence[Path], stride: int | None = None) -> list[Path]:
    """The database images a vocabulary of `dataset` is fitted on: distractor folders left
    out, then every `stride`-th image (default: the map-specific stride)."""
    excluded = set(vocabulary_policies()["exclude_folders"].get(dataset, []))
    kept = [Path(path) for path in database if not excluded.intersection(Path(path).parts[:-1])]
    return kept[:: map_stride(dataset) if stride is None else stride]


def paper_vocabulary(dataset: str) -> str:
    """The source the paper's AnyLoc-VLAD-DINOv2 uses for `dataset`: a domain, or `map-<dataset>`."""
    choice = vocabulary_policies()["paper_vocabulary"].get(dataset, "map")
    return f"{MAP_PREFIX}{dataset}" if choice == "map" else choice


def released_name(source: str) -> str | None:
    """Folder name of the authors' released centres for a vprbench source name, if they released one."""
    return vocabulary_policies()["released"].get(source)


def release() -> dict:
    """The authors' released centres: repository, commit, URL pattern, setting, sha256 per folder."""
    return vocabulary_policies()["release"]


def released_setting() -> tuple[str, int, str, int]:
    r = release()
    return r["backbone"], int(r["layer"]), r["facet"], int(r["clusters"])


def released_path(source: str, cache_dir=None) -> Path | None:
    """Where the released centres of `source` live once downloaded (None: not released)."""
    folder = released_name(source)
    if folder is None or folder not in release()["sha256"]:
        return None
    return vocabulary_dir(*released_setting(), folder, cache_dir) / RELEASED_FILE


def released_url(source: str) -> str:
    r = release()
    return r["url"].format(commit=r["commit"], folder=released_name(source))


def released_sources() -> list[str]:
    """vprbench source names whose released centres have a recorded checksum."""
    return [source for source in vocabulary_policies()["released"] if released_path(source) is not None]


def fetch_released(source: str, cache_dir=None) -> Path:
    """The released c_centers.pt of `source`, downloaded with pooch on first use (sha256-checked);
    a file already in place with the right checksum is used as it is."""
    path = released_path(source, cache_dir)
    if path is None:
        raise VPRBenchError(f"The authors released no centres for {source!r}; released: {', '.join(released_sources())}.")
    import pooch

    url = released_url(source)
    # one download at a time per file: pooch streams it into a tmp* file beside it, so those found then
    # are killed downloads' (pooch never removes them)
    with lock(path.with_name(f".{path.name}.lock"), what=f"the download of {path}"):
        remove_stale(path.parent.glob("tmp*"), age_s=0)
        try:
            pooch.retrieve(url, known_hash=f"sha256:{release()['sha256'][released_name(source)]}", fname=path.name,
                           path=path.parent, progressbar=False)
        except Exception as error:  # network failure or checksum mismatch: say where the file goes
            raise VPRBenchError(
                f"Cannot download the authors' {source!r} centres from {url} ({network_reason(error).rstrip('.')}). "
                f"On a machine with internet access run `vprbench vocabulary download` (or fetch that URL) "
                f"and put the file at {path}."
            ) from None
    return path


def source_datasets(source: str) -> list[str]:
    """The datasets whose databases a vocabulary of the vprbench source name `source` is fitted on:
    map-<dataset>'s one, a domain's or group's members; [] for any other name."""
    if source.startswith(MAP_PREFIX):
        return [source[len(MAP_PREFIX):]]
    return [name for name, _ in domain_datasets(source)] if source in domain_names() else []


def paper_choice(dataset: str, backbone: str, layer: int, facet: str, clusters: int,
                 cache_dir=None, stride: int | None = None) -> tuple[Vocabulary | None, str, str]:
    """(vocabulary or None, source name, note) for the paper's vocabulary of `dataset`.

    None means map-specific: where the paper fits it on the evaluated database (e.g. Mid-Atlantic
    Ridge), or, with a note, where neither a cached nor a released vocabulary of the paper's
    source fits these features (another backbone, layer, facet or cluster count)."""
    source = paper_vocabulary(dataset)
    if source.startswith(MAP_PREFIX):
        return None, source, ""
    found = find_vocabulary(source, backbone, layer, facet, clusters, cache_dir, stride)
    if found is not None:
        check_clusters(found, clusters, source, vocabulary_dir(backbone, layer, facet, found.clusters, source, cache_dir,
                                                               stride))
        return found, source, ""
    if released_path(source) is not None and is_released_setting(backbone, layer, facet, clusters, stride):
        return load_vocabulary(fetch_released(source, cache_dir)), source, ""
    rb, rl, rf, rc = released_setting()
    note = (f"no {source!r} vocabulary for {setting_words(backbone, layer, facet, clusters, stride)} (the authors "
            f"released {rb} layer {rl} {rf} {rc} only; `vprbench vocabulary fit --domain {source}` makes one): "
            f"fitted on the evaluated database of {dataset} (map-specific) instead")
    return None, f"{MAP_PREFIX}{dataset}", note


def find_vocabulary(source: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                    stride: int | None = None) -> Vocabulary | None:
    """A cached vocabulary for these feature settings and source, or None; `stride` None: the
    backbone's own. Its user checks it proves them (`check_proven`) once its size is checked."""
    path = cached_vocabulary_file(source, backbone, layer, facet, clusters, cache_dir, stride)
    found = None if path is None else load_vocabulary(path)
    from .anyloc_provenance import content_source

    if found is not None and (own := content_source(found, source)):
        belongs = vocabulary_dir(backbone, layer, facet, found.clusters, own, cache_dir, stride)
        raise VPRBenchError(f"Vocabulary {path} holds the centres of {own!r} but sits in the cache folder of {source!r}: "
                            f"move it to {belongs} (or delete it), then run again.")
    return found


def cached_vocabulary_file(source: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                           stride: int | None = None) -> Path | None:
    """Our vocabulary.pt in the cache folder of these settings and source, else the authors'
    c_centers.pt under the source name or the authors' folder name (so their released folders can be
    copied into the cache as they are), each also under the folder name used before names were made
    portable; None when there is none."""
    folders = [vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir, stride)]
    old = legacy_vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir, stride)
    folders += [old] if old is not None else []
    released = released_name(source)
    if released:
        folders += [folder.parent / released for folder in folders]
    return next(filter(None, map(vocabulary_file_in, folders)), None)


def is_released_setting(backbone: str, layer: int, facet: str, clusters: int, stride: int | None = None) -> bool:
    """Whether these features are the ones the authors' released centres were fitted on."""
    return (backbone, layer, facet, clusters) == released_setting() and at_default_stride(backbone, stride)


def setting_words(backbone: str, layer: int, facet: str, clusters: int, stride: int | None = None) -> str:
    shown = "" if at_default_stride(backbone, stride) else f" at stride {stride}"
    return f"{backbone} layer {layer} {facet}{shown} with {clusters} clusters"


def check_proven(vocabulary: Vocabulary, backbone: str, layer: int, facet: str, stride: int | None = None) -> None:
    """A cached file is served by its key only for the features it proves it was fitted on. The stride
    is recorded since it is keyed; a file that does not record it (saved before) proves it only as the
    authors' release (by its sha256) or for a backbone that runs at one stride only."""
    from .anyloc_provenance import check_released_setting, released_provenance

    vocabulary.check_setting(backbone, layer, facet, stride)
    check_released_setting(vocabulary, backbone, layer, facet, stride)  # imported under another setting's key
    if vocabulary.meta.get("stride") is not None:
        return

    entry = catalogued(backbone)
    one_stride = entry is not None and entry.one_stride
    released = at_default_stride(backbone, stride) and released_provenance(vocabulary).get("source") == "released"
    if one_stride or released:  # the authors fitted at the backbone's own stride
        return
    asked = default_stride(backbone) if stride is None else stride
    raise VPRBenchError(
        f"Vocabulary {vocabulary.meta.get('path')} does not record the patch stride it was fitted at (saved before "
        f"vprbench keyed vocabularies by stride), so it cannot be served by name to features at stride {asked}: if it "
        f"was fitted at stride {asked}, import it again with `vprbench vocabulary import {vocabulary.meta.get('path')} --source "
        f"{vocabulary.meta.get('source', 'SOURCE')} --backbone {backbone} --layer {layer} --facet {facet} --stride "
        f"{asked}`, else fit it again (`vprbench vocabulary fit`).")


def names_file(option: str) -> bool:
    """Whether the `vocabulary` option names a file or folder rather than a cached source."""
    path = Path(option).expanduser()
    return path.suffix in (".pt", ".npy") or "/" in option or path.exists()


def bare_folder_identity(option: str) -> dict[str, str]:
    """{"vocabulary": "sha256:<hex>"} of the file a folder named by a bare word ('urban' in the authors'
    unpacked release) holds: spec.files takes a bare word for a name, but the method loads that file."""
    from ..content_identity import folder_identity
    from ..weights import file_sha256

    folder = Path(option).expanduser()
    if not folder.is_dir() or folder_identity(option) is not None:
        return {}
    chosen = vocabulary_file_in(folder)
    return {} if chosen is None else {"vocabulary": "sha256:" + file_sha256(chosen)}


def named_identity(option: str, dataset: str, backbone: str, layer: int, facet: str, clusters: int,
                   cache_dir=None, stride: int | None = None) -> str | None:
    """What a vocabulary named by source ("urban", "map-pitts30k", or "domain": the paper's for
    `dataset`) is now, by content and without downloading: the cached file's sha256, else the released
    file's published one, else "map-<dataset>" where "domain" falls back to the evaluated database.
    None: nothing of that name (the run says how to make it). A refit is so another run."""
    from ..weights import file_sha256

    source = paper_vocabulary(dataset) if option == "domain" else option
    if source.startswith(MAP_PREFIX) and option == "domain":
        return source
    path = cached_vocabulary_file(source, backbone, layer, facet, clusters, cache_dir, stride)
    if path is not None:
        return "sha256:" + file_sha256(path)
    if released_path(source) is not None and is_released_setting(backbone, layer, facet, clusters, stride):
        return "sha256:" + release()["sha256"][released_name(source)]
    return f"{MAP_PREFIX}{dataset}" if option == "domain" else None


def save_to_cache(vocabulary: Vocabulary, backbone: str, layer: int, facet: str, source: str, cache_dir=None,
                  stride: int | None = None) -> Path:
    """Cache the centres under the key of the features they were fitted on (`stride` None: the
    backbone's own), which their metadata records (`check_proven` reads it back)."""
    stride = default_stride(backbone) if stride is None else int(stride)
    vocabulary.check_setting(backbone, layer, facet, stride)  # never cached under another setting's key
    meta = {**vocabulary.meta, "backbone": backbone, "layer": layer, "facet": facet, "source": source}
    vocabulary.meta = {**meta, **({"stride": stride} if stride is not None else {})}
    folder = vocabulary_dir(backbone, layer, facet, vocabulary.clusters, source, cache_dir, stride)
    return write_in_turn(folder / VOCABULARY_FILE, vocabulary.save, f"the vocabulary in {folder}")


def resolve_vocabulary(spec: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                       stride: int | None = None) -> Vocabulary:
    """The `vocabulary` option: a file or folder path, or a cached source name
    (a domain, or map-<dataset>). Raises a clear error saying how to create it."""
    if names_file(spec):
        vocabulary = load_vocabulary(Path(spec).expanduser())
    else:
        vocabulary = find_vocabulary(spec, backbone, layer, facet, clusters, cache_dir, stride)
        if vocabulary is not None:
            check_clusters(vocabulary, clusters, spec,
                           vocabulary_dir(backbone, layer, facet, vocabulary.clusters, spec, cache_dir, stride))
            check_folder_known(vocabulary, spec)
        if vocabulary is None and released_path(spec) is not None and is_released_setting(backbone, layer, facet,
                                                                                           clusters, stride):
            vocabulary = load_vocabulary(fetch_released(spec, cache_dir))
        if vocabulary is None:
            where = vocabulary_dir(backbone, layer, facet, clusters, spec, cache_dir, stride)
            if spec.startswith(MAP_PREFIX) or spec in domain_names():
                from ..datasets import dataset_manifests

                name = spec[len(MAP_PREFIX):]
                name = name if name in dataset_manifests() else "YOUR-FOLDER"  # a folder of one's own: by its path
                how = f"--dataset {name}" if spec.startswith(MAP_PREFIX) else f"--domain {spec}"
                how = own_map_names(where) + f"Fit it with `vprbench vocabulary fit --method METHOD {how} ...`"
            else:  # no domain to fit: a typo, or a name only `vocabulary import` gives
                how = (f"{spec!r} is no domain ({', '.join(domain_names())}) nor map-DATASET."
                       f"{closest_names(spec, domain_names())} Name one, or put your centres under this name with "
                       f"`vprbench vocabulary import FILE --source {spec}`")
            released = is_released_setting(backbone, layer, facet, clusters, stride)  # else their centres are refused
            raise VPRBenchError(
                f"No {spec!r} vocabulary for {setting_words(backbone, layer, facet, clusters, stride)} "
                f"(looked in {where}). {how}"
                + (", or pass the path of the authors' released c_centers.pt as the vocabulary." if released else ".")
            )
    check_clusters(vocabulary, clusters, spec)
    return vocabulary


def check_folder_known(vocabulary: Vocabulary, source: str) -> None:
    """Refuse a map vocabulary fitted on a folder of one's own before such names carried its content (the
    folder is unknown: any folder of that name could be served it); one imported under a name is the user's."""
    from ..datasets import dataset_manifests

    name = source[len(MAP_PREFIX):]
    meta = vocabulary.meta
    if (source.startswith(MAP_PREFIX) and name not in dataset_manifests() and "folder" not in meta
            and "imported_from" not in meta and isinstance(meta.get("datasets"), dict) and list(meta["datasets"]) == [name]):
        cached = own_map_names(Path(meta["path"]).parent) if meta.get("path") else ""
        raise VPRBenchError(f"Vocabulary {source!r} ({meta.get('path')}) was fitted on a folder of your own named "
                            f"{name!r} before vprbench named such vocabularies by the folder's content too, so which "
                            f"folder is unknown. {cached}Fit it again (`vprbench vocabulary fit --method METHOD --dataset "
                            f"YOUR-FOLDER ...` with this run's options) and give the name it prints, "
                            f"{source}-<{OWN_CONTENT_DIGITS} hex digits>.")


def own_map_names(where: Path) -> str:
    """The map vocabularies cached beside `where` (map-NAME's folder) for folders of one's own named NAME, whose
    names carry their content too: none is taken for another (two folders may share a name)."""
    found = sorted(where.parent.glob(f"{glob.escape(where.name)}-{'[0-9a-f]' * OWN_CONTENT_DIGITS}"))
    if not found:
        return ""
    fitted = []
    for folder in found:
        try:
            fitted.append(f"{folder.name} (fitted on {load_vocabulary(folder).meta.get('folder', 'a folder')})")
        except VPRBenchError:  # a damaged one is still named
            fitted.append(folder.name)
    return (f"A folder of your own's map vocabulary is named by its content too: cached are {', '.join(fitted)}; "
            "give the one of your folder. ")


def check_clusters(vocabulary: Vocabulary, clusters: int, name: str, belongs: Path | None = None) -> None:
    """Refuse centres of another count; `belongs`: the cache folder of their count, for a file
    found in the folder of another count (copied there by hand)."""
    if vocabulary.clusters != clusters and belongs is not None:
        raise VPRBenchError(
            f"Vocabulary {vocabulary.meta.get('path', name)} has {vocabulary.clusters} clusters but sits in the cache "
            f"folder of {clusters}-cluster vocabularies: move it to {belongs} (or delete it) and fit one of {clusters} "
            "(`vprbench vocabulary fit`).")
    if vocabulary.clusters != clusters:
        raise VPRBenchError(
            f"Vocabulary {vocabulary.meta.get('path', name)} has {vocabulary.clusters} clusters, "
            f"the method asks for {clusters}: give --clusters {vocabulary.clusters} to use it, or fit one of "
            f"{clusters} (`vprbench vocabulary fit`)."
        )
