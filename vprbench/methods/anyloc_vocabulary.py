"""AnyLoc's vocabulary policy: which images a VLAD vocabulary is fitted on (map-specific
and domain vocabularies), the authors' released centres, and the `vocabulary` option's names:
where a vocabulary of a name is cached, and what it is by content.

Domain membership is data (manifests/vocabularies.toml); fitting is anyloc_fit.py; what a file's
content says it is (the release by sha256, a fit's metadata) is anyloc_provenance.py; finding the
vocabulary a run asks for, checked against that, is anyloc_lookup.py.
"""
from __future__ import annotations

import tomllib
from functools import cache
from importlib.resources import files
from pathlib import Path
from typing import Sequence

from ..aggregation.vocabulary import (
    RELEASED_FILE, VOCABULARY_FILE, Vocabulary, at_default_stride, default_stride, legacy_vocabulary_dir, vocabulary_dir,
    vocabulary_file_in,
)
from ..errors import VPRBenchError, closest_names, network_reason
from ..fsutil import lock, remove_stale, write_in_turn

MAP_PREFIX = "map-"
#: hex digits of a folder of one's own's database content in its map vocabulary's name
OWN_CONTENT_DIGITS = 12


@cache
def vocabulary_policies() -> dict:
    return tomllib.loads((files("vprbench.manifests") / "vocabularies.toml").read_text(encoding="utf-8"))


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


def cached_vocabulary_file(source: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                           stride: int | None = None) -> Path | None:
    """Our vocabulary.pt in the cache folder of these settings and source, else the authors'
    c_centers.pt under the source name or the authors' folder name (so their released folders can be
    copied into the cache as they are), each also under the folder name used before names were made
    portable; None when there is none. For the release's own names and setting the release's
    c_centers.pt is read first: centres fitted or imported under its name never pass for it once it is
    here (they are read only where it is not, and recorded as not the release)."""
    folders = [vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir, stride)]
    old = legacy_vocabulary_dir(backbone, layer, facet, clusters, source, cache_dir, stride)
    folders += [old] if old is not None else []
    released = released_name(source)
    if released:
        folders += [folder.parent / released for folder in folders]
    if released and is_released_setting(backbone, layer, facet, clusters, stride):
        first = next((folder / RELEASED_FILE for folder in folders if (folder / RELEASED_FILE).is_file()), None)
        if first is not None:
            return first
    return next(filter(None, map(vocabulary_file_in, folders)), None)


def is_released_setting(backbone: str, layer: int, facet: str, clusters: int, stride: int | None = None) -> bool:
    """Whether these features are the ones the authors' released centres were fitted on."""
    return (backbone, layer, facet, clusters) == released_setting() and at_default_stride(backbone, stride)


def setting_words(backbone: str, layer: int, facet: str, clusters: int, stride: int | None = None) -> str:
    shown = "" if at_default_stride(backbone, stride) else f" at stride {stride}"
    return f"{backbone} layer {layer} {facet}{shown} with {clusters} clusters"


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
