"""A vocabulary found for a run (the `vocabulary` option, the paper's choice for a dataset): in the cache,
served only for the features its content proves it was fitted on (anyloc_provenance.py), else the
authors' release; refused, with how to make it, when there is none.

The policy it follows (domains, the release, cache keys) is anyloc_vocabulary.py.
"""
from __future__ import annotations

import glob
import shlex
from pathlib import Path

from ..aggregation.vocabulary import Vocabulary, at_default_stride, catalogued, default_stride, load_vocabulary, vocabulary_dir
from ..errors import MethodNeed, VPRBenchError, closest_names
from .anyloc_provenance import check_released_setting, content_source, released_provenance
from .anyloc_vocabulary import (MAP_PREFIX, OWN_CONTENT_DIGITS, cached_vocabulary_file, domain_names, fetch_released,
                                is_released_setting, names_file, paper_vocabulary, released_path, released_setting,
                                setting_words)


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
    if found is not None and (own := content_source(found, source)):
        belongs = vocabulary_dir(backbone, layer, facet, found.clusters, own, cache_dir, stride)
        raise VPRBenchError(f"Vocabulary {path} holds the centres of {own!r} but sits in the cache folder of {source!r}: "
                            f"move it to {belongs} (or delete it), then run again.")
    return found


def check_proven(vocabulary: Vocabulary, backbone: str, layer: int, facet: str, stride: int | None = None) -> None:
    """A cached file is served by its key only for the features it proves it was fitted on. The stride
    is recorded since it is keyed; a file that does not record it (saved before) proves it only as the
    authors' release (by its sha256) or for a backbone that runs at one stride only."""
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


def fit_options(method) -> dict:
    """The options an AnyLoc's vocabularies are keyed by, as `vprbench vocabulary fit` takes them (its weights
    key them too: random or a checkpoint of one's own; a stride only off the backbone's own)."""
    stride = None if at_default_stride(method.backbone, method.stride) else f"stride={method.stride}"
    return {"backbone": method.backbone, "weights": method.weights, "layer": method.layer, "facet": method.facet,
            "clusters": method.clusters, "option": stride}


def fit_command(method: str, source: str, options: dict, locations: dict | None = None) -> str:
    """The `vprbench vocabulary fit` making the vocabulary `source` (a domain, or map-DATASET) with `method` and
    the `options` it is keyed by (`fit_options`; None: unset), from and into the run's `locations`
    ({"data-dir": ..., "cache-dir": ...}; else the defaults, where that run does not look): one to paste."""
    on = ["--dataset", source[len(MAP_PREFIX):]] if source.startswith(MAP_PREFIX) else ["--domain", source]
    given = [word for flag, value in {**options, **(locations or {})}.items() if value is not None
             for word in (f"--{flag}", str(value))]
    return shlex.join(["vprbench", "vocabulary", "fit", *on, "--method", method, *given])


def resolve_vocabulary(spec: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                       stride: int | None = None, fit: dict | None = None) -> Vocabulary:
    """The `vocabulary` option: a file or folder path, or a cached source name
    (a domain, or map-<dataset>). Raises a clear error saying how to create it: with `fit` (`fit_options`,
    else these arguments) for a domain or map vocabulary, which create_method completes (MethodNeed)."""
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
            raise no_vocabulary(spec, backbone, layer, facet, clusters, cache_dir, stride, fit)
    check_clusters(vocabulary, clusters, spec)
    return vocabulary


def no_vocabulary(spec: str, backbone: str, layer: int, facet: str, clusters: int, cache_dir=None,
                  stride: int | None = None, fit: dict | None = None) -> VPRBenchError:
    """The refusal of a named vocabulary not here, with how to make it: a domain's or a map's by the command
    fitting it (`fit`: `fit_options`, else these arguments), which create_method says again naming the preset
    it made and the run's folders (MethodNeed); another name by `vocabulary import`."""
    from ..datasets import dataset_manifests

    where = vocabulary_dir(backbone, layer, facet, clusters, spec, cache_dir, stride)
    said = f"No {spec!r} vocabulary for {setting_words(backbone, layer, facet, clusters, stride)} (looked in {where}). "
    released = is_released_setting(backbone, layer, facet, clusters, stride)  # else their centres are refused
    tail = ", or pass the path of the authors' released c_centers.pt as the vocabulary." if released else "."
    if not spec.startswith(MAP_PREFIX) and spec not in domain_names():  # a typo, or a name only import gives
        return VPRBenchError(f"{said}{spec!r} is no domain ({', '.join(domain_names())}) nor map-DATASET."
                             f"{closest_names(spec, domain_names())} Name one, or put your centres under this name "
                             f"with `vprbench vocabulary import FILE --source {spec}`{tail}")
    known = spec in domain_names() or spec[len(MAP_PREFIX):] in dataset_manifests()
    source = spec if known else f"{MAP_PREFIX}YOUR-FOLDER"  # a folder of one's own: fitted by its path
    name, _, weights = backbone.partition("@")  # BACKBONE@random: random weights' own key
    options = fit or {"backbone": name, "weights": weights or None, "layer": layer, "facet": facet, "clusters": clusters,
                      "option": None if at_default_stride(backbone, stride) else f"stride={stride}"}
    said += own_map_names(where)
    # 'anyloc': the method these options make, until create_method names the preset it made
    return MethodNeed(lambda method, locations: f"{said}Fit it with `{fit_command(method, source, options, locations)}`"
                                                f"{tail}", "anyloc")


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
