"""What a paper table's cell lacks on this machine, before anything runs: its datasets (on disk, in
their layout), its weights, its vocabulary (released, cached and usable, or to fit) and the memory
its PCA-whitening needs; each with how to get it. Used by `reproduce` (dry run and run)."""
from __future__ import annotations

from ..errors import VPRBenchError
from .plan import Cell

#: what a cell lacks: (the thing, how to get it), e.g. ("dataset hawkins", "Download ...")
Need = tuple[str, str]


def row_source(row_weights: dict):
    """A plan row's `weights` (file + url, hub or page, as its authors publish it) as the resolver's source."""
    from ..weight_source import WeightSource

    return WeightSource(row_weights["file"], url=row_weights.get("url"), hub=row_weights.get("hub"),
                        page=row_weights.get("page"))


def placed_weights(row: dict, cache_dir=None) -> dict:
    """{"weights": path} for a row whose checkpoint has no download (a Google Drive page) once the file
    is where the dry run says to put it: the run cannot fetch it, and reproduce takes no weights option."""
    from ..weights import weights_folder

    source = row_source(row["weights"]) if row.get("weights") else None
    if source is None or source.url or source.hub:
        return {}
    path = weights_folder(cache_dir) / source.file_name
    return {"weights": str(path)} if path.is_file() else {}


def how_to_fetch(source, cache_dir=None) -> str:
    """Where the run reads `source`'s file, and how to put it there first (a compute node may be offline)."""
    from ..weights import hub_folder, weights_folder

    if source.url or source.hub:
        into = f"{weights_folder(cache_dir) / source.file_name}" if source.url else f"the hub cache {hub_folder(cache_dir)}"
        return (f"let vprbench download {source.where} (a run online with this cache), or put the file at {into}: "
                f"{by_hand(source)}")
    return (f"download it from {source.where} (no direct download) and put it at "
            f"{weights_folder(cache_dir) / source.file_name} ({by_hand(source)})")


def by_hand(source) -> str:
    """What a file put in the cache by hand is (official only by a published sha256, `weights.cached_identity`)."""
    if source.sha256:
        return (f"one put there by hand is the official release only if its sha256 is the published "
                f"{source.sha256.lower()}, else your own weights (a † 'user weights' row)")
    return ("the authors publish no sha256, so one put there by hand runs as your own weights, as with --weights "
            "(a † 'user weights' row, not the official one)")


def weights_for(row_weights: dict | None, cell: Cell, cache_dir=None) -> Need | None:
    """What is missing of the cell's weights (None: present, or not knowable before running)."""
    from ..features.catalogue import backbone_spec
    from ..methods.anyloc import AnyLoc
    from ..methods.registry import method_entry
    from ..weights import cached_weights, local_weights

    entry = method_entry(cell.spec.method)
    merged = {**entry.defaults, **cell.spec.given}
    if entry.factory is AnyLoc:
        spec = backbone_spec(merged.get("backbone", "dinov2_vitg14"))
        if merged.get("weights"):
            try:
                local_weights(spec.source, merged["weights"], f"backbone {spec.name}")
                return None
            except VPRBenchError as error:
                return f"weights {merged['weights']}", str(error)
        if cached_weights(spec.source, cache_dir) is not None:
            return None
        if spec.gated:
            return (f"weights of {spec.name}", f"gated, {spec.licence}: request access at {spec.page}; "
                    f"then downloaded from {spec.source.where} on first use")
        return f"weights {weights_name(spec.source)}", how_to_fetch(spec.source, cache_dir)
    if merged.get("weights") or not row_weights:
        return None
    # where the run looks, as it looks (not "pass weights=PATH": reproduce refuses method options)
    source = row_source(row_weights)
    return None if cached_weights(source, cache_dir) else (f"weights {weights_name(source)}", how_to_fetch(source, cache_dir))


def weights_name(source) -> str:
    """A checkpoint as a need names it: a hub's by its repository too (timm's are all model.safetensors)."""
    return f"{source.hub}/{source.file_name}" if source.hub else source.file_name


def vocabulary_for(cell: Cell, cache_dir=None, given: dict | None = None) -> Need | None:
    """A domain or union vocabulary (`domain`: the paper's choice for the cell's dataset) that is
    neither cached nor released for the cell's features must be fitted first. `given`: the run's
    own locations ({"data-dir": ..., "cache-dir": ...}), carried into the fit command, which
    would otherwise fit from and into the default ones."""
    import shlex
    import warnings

    from ..aggregation.vocabulary import at_default_stride
    from ..methods.anyloc import VLADS, AnyLoc
    from ..methods.anyloc_lookup import check_clusters, check_proven, find_vocabulary, fit_command, fit_options
    from ..methods.anyloc_provenance import released_as
    from ..methods.anyloc_vocabulary import (domain_names, is_released_setting, paper_vocabulary, released_path,
                                             setting_words)
    from ..methods.registry import method_entry

    entry = method_entry(cell.spec.method)
    if entry.factory is not AnyLoc:
        return None
    options = {**entry.effective_defaults(), **cell.spec.options}  # a default is not written in a spec
    name = options.get("vocabulary")
    if options.get("aggregation") not in VLADS:
        return None
    if name == "domain":
        name = paper_vocabulary(cell.spec.dataset.name)
    if not isinstance(name, str) or name not in domain_names() and released_path(name) is None:
        return None  # fitted on the map at run time, or a file
    with warnings.catch_warnings():  # a preset's layer on another backbone: the same relative depth
        warnings.simplefilter("ignore")
        method = AnyLoc(**{**options, "vocabulary": "map"}, cache_dir=cache_dir)  # the cell's features; nothing loads
    setting = (method.vocabulary_backbone, method.layer, method.facet, method.clusters)
    released = released_path(name, cache_dir) if is_released_setting(*setting, method.stride) else None
    try:  # what the run checks of a cached file: one it would refuse is a need here, not "would run"
        found = find_vocabulary(name, *setting, cache_dir, method.stride)
        if found is not None:
            check_clusters(found, method.clusters, name)
            found.check_dim(method.spec.width)
            check_proven(found, *setting[:3], method.stride)
    except VPRBenchError as error:
        return f"the cached vocabulary {name!r} for {setting_words(*setting, method.stride)}", str(error)
    # centres of one's own under the release's name serve only until the release is here (then read first)
    own = found is not None and released is not None and released_as(found) is None
    if not own and (found is not None or (released is not None and released.is_file())):
        return None  # cached, or the authors' release already here
    located = [(flag, shlex.quote(str(path))) for flag, path in (given or {}).items() if path is not None]
    if released is not None:  # fetched before the run, as weights are (a compute node may be offline)
        # `vocabulary download` reads no data: only the cache it fills is carried into the command
        into = "".join(f" --{flag} {path}" for flag, path in located if flag == "cache-dir")
        mine = (f"the centres cached as {name!r} ({found.meta.get('path')}) are not the authors' release (fitted or "
                "imported here) and would run as a † row; " if own else "")
        return (f"the authors' vocabulary {name!r}", f"{mine}run 'vprbench vocabulary download{into}', or put the "
                f"release's c_centers.pt at {released}" + (" (read first under that name)" if own else ""))
    if name not in domain_names():
        return None
    # named by its cache key (not the method's: cells of several methods share it, once_each says it once)
    stride = "" if at_default_stride(method.backbone, method.stride) else f" stride {method.stride}"
    return (f"vocabulary {name!r} for {setting[0]} layer {method.layer} {method.facet} c{method.clusters}{stride}",
            f"run '{fit_command(cell.spec.method, name, fit_options(method), given)}'")


def memory_for(cell: Cell, memory_budget: int | None = None) -> Need | None:
    """AnyLoc's PCA-whitening fitted exactly (docs/anyloc.md, PCA-whitening): a memory budget too small for
    the database rows it is fitted on (their count from the manifests, their width from the features)
    is said before hours of description, not at the fit."""
    from ..aggregation.pca import PCAWhitening
    from ..evaluation.postprocess import RowShape
    from ..methods.anyloc import VLADS, AnyLoc
    from ..methods.anyloc_options import probe
    from ..methods.registry import method_entry
    from ..row_sources import DEFAULT_MEMORY_BUDGET, format_budget, format_bytes

    entry, names = method_entry(cell.spec.method), pca_stack(cell)
    # the cell's features, nothing loaded (a default is not written in a spec); None: an option its run refuses
    method = probe(AnyLoc, {**entry.effective_defaults(), **cell.spec.options}) if entry.factory is AnyLoc else None
    if method is None or not names:
        return None
    rows, dim = stack_images(cell, names), method.spec.width * (method.clusters if method.aggregation in VLADS else 1)
    need = PCAWhitening(method.pca_dim).exact_memory(RowShape({"count": rows, "dim": dim, "dtype": cell.spec.store_dtype}))
    budget = memory_budget or DEFAULT_MEMORY_BUDGET
    if need <= budget:
        return None
    # named by all the need depends on: cells of a plan needing it are told one budget (once_each)
    return (f"memory for PCA-whitening of {rows:,} x {dim:,} descriptors to {method.pca_dim}",
            f"run with --search-memory {format_budget(need)} or more, so the PCA is fitted exactly, not by randomized "
            f"iteration ({format_bytes(budget)} given)")


def missing_for(cell: Cell, row_weights, data_dir=None, cache_dir=None, given: dict | None = None,
                memory_budget: int | None = None) -> list[Need]:
    """Everything the cell lacks on this machine, none when it can run (`given`: as vocabulary_for;
    `memory_budget`: the run's)."""
    from ..datasets import dataset_location, dataset_manifest
    from ..datasets.layouts import detect_layout
    from ..datasets.locations import how_to_get

    needs = []
    if cell.spec.dataset.kind == "benchmark":  # with the other databases its PCA is fitted on (pca_on = "domain")
        for name in pca_stack(cell) or [cell.spec.dataset.name]:
            manifest = dataset_manifest(name)
            root = dataset_location(manifest, data_dir)
            if not root.is_dir():
                needs.append((f"dataset {name}", how_to_get(manifest, data_dir)))
                continue
            try:  # a folder without its layout's files (an unfinished extraction): the run's refusal, said now
                detect_layout(root, manifest, data_dir)
            except VPRBenchError as error:
                needs.append((f"dataset {name}", str(error)))
    return needs + [need for need in (weights_for(row_weights, cell, cache_dir), vocabulary_for(cell, cache_dir, given),
                                      memory_for(cell, memory_budget)) if need]


def pca_stack(cell: Cell) -> list[str]:
    """The benchmarks whose databases the cell's PCA-whitening is fitted on: the evaluated one, or with
    pca_on = "domain" its domain's; none without PCA or on a dataset that is no benchmark."""
    from ..methods.anyloc_options import pca_datasets

    dataset = cell.spec.dataset
    if not cell.spec.options.get("pca_dim") or dataset.kind != "benchmark":
        return []
    joint = pca_datasets(cell.spec.options.get("pca_on", "database"), dataset.name)
    return joint[1] if joint else [dataset.name]


def stack_images(cell: Cell, names: list[str]) -> int:
    """The database images of `names` (the cell's dataset at its protocol, the others at their default)."""
    dataset = cell.spec.dataset
    return sum(_database_count(name, dataset.protocol if name == dataset.name else None) for name in names)


def _database_count(name: str, protocol) -> int:
    from ..datasets import dataset_manifest, find_protocol

    manifest = dataset_manifest(name)
    found = find_protocol(manifest, protocol)
    return found.database_count or (manifest.query_count if found.swap else manifest.database_count) or 0


def once_each(missing: dict[str, list[Need]], rows: dict[str, str]) -> dict[str, list[Need]]:
    """The needs of a plan's cells (by cell key) with each thing said one way, so it is listed and got once:
    a domain vocabulary is cached by its features, not by the method fitting it, so the cells of two methods
    (AnyLoc-VLAD-DINO and its -PCA) lacking it get the first's fit, naming the rows it serves (`rows`: each
    cell's)."""
    hows: dict[str, dict[str, None]] = {}
    served: dict[str, dict[str, None]] = {}
    for key, needs in missing.items():
        for thing, how in needs:
            hows.setdefault(thing, {})[how] = None
            served.setdefault(thing, {})[rows[key]] = None
    said = {thing: next(iter(ways)) + (f" (serves rows {', '.join(served[thing])})" if len(ways) > 1 else "")
            for thing, ways in hows.items()}
    return {key: [(thing, said[thing]) for thing, _ in needs] for key, needs in missing.items()}


def needs_text(needs: list[Need]) -> str:
    """The needs in one line, each with how to get it."""
    return "; ".join(f"{thing} ({how})" for thing, how in needs)
