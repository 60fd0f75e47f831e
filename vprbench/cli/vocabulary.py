"""`vprbench vocabulary`: fit, import, show, list and download VLAD vocabularies.

Wired like the other command modules: `add_parsers(commands)`; each subcommand sets `run`.
Fitting needs a method whose `iter_patch_features(paths, resize)` yields each image's
(N, D) patch features as they enter VLAD (AnyLoc provides it).
"""
from __future__ import annotations

import re

# The vocabulary machinery (torch) is imported by each subcommand, so `vprbench --help` answers at once.
from ..errors import VPRBenchError
from ..text import one_line, shortened
from .console import say
from .options import (add_location_options, add_method_options, method_options, output_file, path_argument, progress,
                      resolve_locations)

#: at most this many characters of a vocabulary file's value are shown (a domain's datasets fit in it)
SHOWN_LIMIT = 400


def add_parsers(commands) -> None:
    parser = commands.add_parser("vocabulary", help="fit, import, download, show and list VLAD vocabularies")
    sub = parser.add_subparsers(dest="vocabulary_command", required=True, metavar="COMMAND")

    p = sub.add_parser("fit", help="fit a domain or map-specific vocabulary with a method's features")
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument("--domain", help="a domain or group of domains (`vprbench vocabulary domains` lists them)")
    which.add_argument("--dataset", help="map-specific: the dataset's own database")
    p.add_argument("--budget", type=int, help="features kept by the seeded sampler (default 250,000)")
    p.add_argument("--exact", action="store_true", help="the authors' fit on every patch (memory grows with the data)")
    p.add_argument("--seed", type=int, default=42,
                   help="seed of the sampler and of k-means' initial centres (default 42, the authors')")
    p.add_argument("--output", type=output_file(".pt"), help="also write the vocabulary file (.pt) here")
    p.add_argument("--quiet", action="store_true",
                   help="no progress (without a terminal, progress is a line to stderr at most every 30 s)")
    add_location_options(p)
    add_method_options(p)
    p.set_defaults(run=run_fit)

    p = sub.add_parser("import", help="put a vocabulary file (e.g. the authors' c_centers.pt) in the cache by name")
    p.add_argument("path", type=path_argument)
    p.add_argument("--source", required=True, help="domain name or map-<dataset>")
    p.add_argument("--backbone", default="dinov2_vitg14",
                   help="the features the centres fit: BACKBONE, BACKBONE@random, or BACKBONE@<16 hex of your "
                        "checkpoint's sha256 (default: dinov2_vitg14, the authors' release; a file that names its "
                        "features must match them)")
    p.add_argument("--layer", type=int, default=31, help="0-based block the centres were fitted on (default: 31)")
    p.add_argument("--facet", default="value", help="facet the centres were fitted on (default: value)")
    p.add_argument("--stride", type=int, help="the patch stride the centres were fitted at (default: the backbone's own)")
    add_location_options(p, data=False)
    p.set_defaults(run=run_import)

    p = sub.add_parser("show", help="print a vocabulary file's shape, what it was fitted on, and its metadata")
    p.add_argument("path", type=path_argument)
    p.set_defaults(run=run_show)

    p = sub.add_parser("list", help="every vocabulary in the cache: setting, name, size and what it was fitted on")
    p.add_argument("--cache-dir", help="where descriptor stores, vocabularies and results live "
                                       "(default: $VPRBENCH_CACHE or the user cache)")
    p.set_defaults(run=run_list)

    p = sub.add_parser("domains", help="list the domain vocabularies and their datasets")
    p.set_defaults(run=run_domains)

    p = sub.add_parser("download", help="fetch the authors' released centres ahead of time (sha256-checked)")
    add_location_options(p, data=False)
    p.set_defaults(run=run_download)


def run_fit(args) -> int:
    from ..methods.anyloc_fit import fit_domain_vocabulary, fit_map_vocabulary
    from ..methods.anyloc_vocabulary import domain_image_size, save_to_cache
    from ..aggregation.kmeans import DEFAULT_BUDGET
    from ..methods import create_method
    from ..methods.attributes import use_dataset
    from ..methods.anyloc import VLADS
    from ..methods.registry import method_entry

    resolve_locations(args)
    options = method_options(args)
    # a name or file names centres to use; a fit makes them, so it was ignored ('domain' and 'map' are modes)
    if options.get("vocabulary", "map") not in ("domain", "map"):
        raise VPRBenchError(f"vocabulary fit: --vocabulary {options['vocabulary']} names centres to use, and a fit "
                            "makes them; drop it (--domain or --dataset says what to fit on).")
    # from the options, before the method is made (which refuses --clusters beside a GeM or CLS aggregation)
    try:
        defaults = method_entry(args.method).effective_defaults()
    except VPRBenchError:  # an unknown method: create_method below names it
        defaults = {}
    aggregation = {**defaults, **{k: v for k, v in options.items() if v is not None}}.get("aggregation")
    if aggregation is not None and aggregation not in VLADS:
        # its patch features are not VLAD's (DINO: not normalised; CLS: the last block's tokens), yet the
        # centres would be cached under the VLAD key of this backbone, layer and facet
        raise VPRBenchError(f"vocabulary fit: method {args.method} has aggregation={aggregation}, which uses no "
                            "vocabulary and reads other features than VLAD; give --aggregation "
                            f"{' or '.join(VLADS)}.")
    method = create_method(args.method, **options, cache_dir=args.cache_dir)
    if not hasattr(method, "iter_patch_features"):
        raise VPRBenchError(f"Method {args.method!r} does not expose patch features, so it cannot fit a vocabulary.")
    check_fit_sizes(args, getattr(getattr(method, "spec", None), "width", None))
    clusters = int(method.clusters)
    backbone = getattr(method, "vocabulary_backbone", method.backbone)  # random weights have their own key
    setting = {"backbone": backbone, "layer": method.layer, "facet": method.facet, "stride": getattr(method, "stride", None)}
    if args.domain is None:  # its database described as a run on it describes it (AnyLoc: the dataset's resize)
        if getattr(method, "vocabulary", None) == "domain":  # a fit makes centres: none is looked for (or fetched)
            method.vocabulary = "map"
        use_dataset(method, args.dataset)
    # the resize is not keyed (a domain's centres serve each dataset at its own size, as the paper's): recorded
    resize = getattr(method, "resize", None)
    meta = {**setting, **({} if args.domain is not None else {"resize": list(resize) if resize else "native"})}
    common = {"cache_dir": args.cache_dir, "exact": args.exact, "budget": DEFAULT_BUDGET if args.budget is None else args.budget, "seed": args.seed, "meta": meta}
    data_dir = args.data_dir
    size = domain_image_size() if args.domain is not None else None  # None: the dataset's own (the method's resize)
    # the features per image where the resize fixes them: too many clusters are refused before any is described
    common["per_image"] = method.patches_per_image(size) if hasattr(method, "patches_per_image") else None
    with progress(args) as shown:
        if args.domain is not None:  # '' is an unknown domain, not a map-specific fit
            vocabulary = fit_domain_vocabulary(
                args.domain, lambda paths: _patch_features(method, paths, size), clusters,
                data_dir=data_dir, progress=shown, **common)
            source = args.domain
        else:
            vocabulary = fit_map_vocabulary(
                args.dataset, lambda paths: _patch_features(method, paths, None), clusters,
                data_dir=data_dir, progress=shown, **common)
            source = vocabulary.meta["source"]  # map-<the dataset's name> (a folder's: and its content's)
    path = save_to_cache(vocabulary, source=source, **setting, cache_dir=args.cache_dir)
    print(f"Vocabulary {source}: {vocabulary.clusters} x {vocabulary.dim}, "
          f"{vocabulary.meta['features_used']} of {vocabulary.meta['features_seen']} features -> {path}")
    if args.output:
        print(f"Also written to {vocabulary.save(args.output)}")
    release_note(source, path, clusters=clusters, **setting)
    return 0


def _patch_features(method, paths, resize):
    """`method.iter_patch_features`, what a plugin's raises as one line (`plugin_part`) and only that: the fit
    consuming the features is vprbench's own code."""
    from ..loader import plugin_part

    with plugin_part(method, "iter_patch_features"):
        yield from method.iter_patch_features(paths, resize=resize)


def check_fit_sizes(args, width: int | None) -> None:
    """--budget against this machine's memory and --exact, before any image is read (the
    sample is allocated at the first image; the seed is checked where the fit starts)."""
    from ..aggregation.kmeans import DEFAULT_BUDGET
    from ..evaluation.provenance import memory_bytes
    from ..row_sources import format_bytes

    if args.exact and args.budget is not None:
        raise VPRBenchError("--budget bounds the sampled fit and --exact fits on every patch: give one of them.")
    budget = DEFAULT_BUDGET if args.budget is None else args.budget
    if budget < 1:
        raise VPRBenchError(f"--budget takes a whole number >= 1 (the features kept for the fit), got {budget}.")
    memory = memory_bytes()
    if not args.exact and width and memory and budget * width * 4 > memory:  # the sample is budget x width float32
        raise VPRBenchError(f"--budget {budget:,} keeps {budget:,} features of {width} floats "
                            f"({format_bytes(budget * width * 4)}), more than this machine's memory "
                            f"({format_bytes(memory)}): give a smaller --budget (default {DEFAULT_BUDGET:,}).")


def run_import(args) -> int:
    from pathlib import Path

    from ..methods.anyloc_provenance import check_released_setting, content_source
    from ..methods.anyloc_vocabulary import is_released_setting, release, save_to_cache
    from ..aggregation.vocabulary import load_vocabulary, vocabulary_dir, vocabulary_file_in
    from ..weights import file_sha256
    from ..features.backbones import RANDOM
    from ..features.catalogue import backbone_spec
    from ..methods.checks import choice, whole

    resolve_locations(args)
    # the cache key names features that exist and fit the centres: a backbone, or its random weights
    # (BACKBONE@random) or a user's checkpoint (BACKBONE@<16 hex of its sha256>)
    name, _, weights = args.backbone.partition("@")
    if weights and not re.fullmatch(rf"{RANDOM}|[0-9a-f]{{16}}", weights):
        raise VPRBenchError(f"--backbone {args.backbone!r}: after '@' give 'random' or the first 16 hex digits of "
                            "your checkpoint's sha256 (`sha256sum FILE`), the weights the centres were fitted with.")
    spec = backbone_spec(name)
    whole("vocabulary import", "--layer", args.layer, 0, spec.depth - 1, f"0-based block of {spec.name}")
    choice("vocabulary import", "--facet", args.facet, spec.facets)
    stride = spec.default_stride if args.stride is None else args.stride
    if spec.patch % whole("vocabulary import", "--stride", stride, 1, spec.patch, f"pixels, at most the patch {spec.patch}"):
        raise VPRBenchError(f"--stride {stride} does not divide the patch {spec.patch} of {spec.name}: give one of "
                            + ", ".join(str(d) for d in range(1, spec.patch + 1) if spec.patch % d == 0) + ".")
    check_source(args.source)
    vocabulary = load_vocabulary(args.path)
    vocabulary.check_dim(spec.width)
    if own := content_source(vocabulary, args.source):
        raise VPRBenchError(f"{args.path} holds the centres of {own!r}, not of {args.source!r}: import it with "
                            f"--source {own} (or under a name of your own).")
    # the authors' file names no setting, its sha256 does: never cached as another block's, facet's or weights'
    check_released_setting(vocabulary, args.backbone, args.layer, args.facet, stride)
    source_file = Path(vocabulary.meta["path"])
    released = is_released_setting(args.backbone, args.layer, args.facet, vocabulary.clusters, stride)
    folder = vocabulary_dir(args.backbone, args.layer, args.facet, vocabulary.clusters, args.source, args.cache_dir, stride)
    replaced = vocabulary_file_in(folder) is not None
    if released and file_sha256(source_file) in release()["sha256"].values():
        # the authors' file for their setting, placed as it is: a run naming it keeps its key (their
        # published sha256); under another setting it is saved with the metadata that names it
        path = place_release(folder, source_file.read_bytes())
    else:
        vocabulary.meta["imported_from"] = vocabulary.meta.pop("path")
        path = save_to_cache(vocabulary, args.backbone, args.layer, args.facet, args.source, args.cache_dir, stride)
    # a second import under one name replaces the first: said, as runs naming it now give other results
    again = f" (replacing the centres cached as {args.source!r} before; runs naming it are run again)" if replaced else ""
    print(f"Imported {vocabulary.clusters} x {vocabulary.dim} centres as {args.source!r} -> {path}{again}")
    if "imported_from" in vocabulary.meta:  # not the release placed as it is
        release_note(args.source, path, args.backbone, args.layer, args.facet, vocabulary.clusters, stride)
    return 0


def release_note(source: str, path, backbone: str, layer: int, facet: str, clusters: int, stride=None) -> None:
    """Centres of one's own cached under a name of the authors' release at their setting: said once, as they do
    not pass for the release (the release is read first where it is here)."""
    from ..methods.anyloc_vocabulary import is_released_setting, released_name

    if released_name(source) and is_released_setting(backbone, layer, facet, clusters, stride):
        say(one_line(f"Note: {source!r} names the authors' released centres: runs read theirs first where they are in "
                     "the cache (`vprbench vocabulary download`); these are read under that name only without them, "
                     f"recorded as not the release (a † row on the leaderboard). To use these beside the release, pass "
                     f"--vocabulary {path}."))


def place_release(folder, data: bytes):
    """The authors' file put in `folder` as it is, where the folder is read from: under their own name, or over our
    vocabulary.pt when one is there (fitted or imported before, or by a fit that ended meanwhile), which is read first
    and would hide it. Under that file's lock, as fits write it: the check and the write are one step for them, and the
    file is replaced whole, so a run reading the folder meanwhile finds the old centres or the new, never neither."""
    from ..aggregation.vocabulary import RELEASED_FILE, VOCABULARY_FILE
    from ..fsutil import atomic_write, write_in_turn

    def place(ours):
        if ours.is_file():
            placed.append(atomic_write(ours, data))
        else:  # its own name has its own lock too: downloads of the release write it
            placed.append(write_in_turn(folder / RELEASED_FILE, lambda into: atomic_write(into, data),
                                        f"the vocabulary {folder / RELEASED_FILE}"))

    placed = []
    write_in_turn(folder / VOCABULARY_FILE, place, f"the vocabulary in {folder}")
    return placed[0]


def check_source(source: str) -> None:
    """A name `import` may cache centres under (a folder's name, given back by runs' --vocabulary): map-DATASET
    with a dataset's name (a folder of one's own's followed by its content's digits, as its fit names it), or
    another plain name."""
    from ..datasets.layouts.own_data import NAME_RULE, is_safe_name
    from ..methods.anyloc_vocabulary import MAP_PREFIX, OWN_CONTENT_DIGITS

    if source.startswith(MAP_PREFIX):
        ok = is_safe_name(re.sub(rf"-[0-9a-f]{{{OWN_CONTENT_DIGITS}}}$", "", source[len(MAP_PREFIX):]))
    else:
        ok = re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_-]{0,99}", source) is not None
    if not ok:
        raise VPRBenchError(f"--source {source!r} is not a vocabulary name: give a domain (`vprbench vocabulary "
                            f"domains`), map-DATASET with a dataset's name ({NAME_RULE}), or another name of 1 to 100 "
                            "letters, digits, '_' or '-' starting with a letter or digit.")


def run_show(args) -> int:
    from ..aggregation.vocabulary import load_vocabulary

    vocabulary = load_vocabulary(args.path)
    say(one_line(f"{vocabulary.meta['path']}: {vocabulary.clusters} clusters x {vocabulary.dim} dims"))
    say(f"  fitted on: {fitted_on(vocabulary)}")
    for key, value in sorted(vocabulary.meta.items()):  # a file's metadata: text from data, one line per key
        if key == "image_digests" and isinstance(value, bytes):  # a folder's fit: one sha256 per image, counted
            value = (f"{len(value) // 32} sha256 (of the images fitted on)" if len(value) % 32 == 0 else
                     f"{len(value)} bytes, not whole sha256 (unusable: runs do not know the images fitted on)")
        say(f"  {shown(key)}: {shown(value)}")
    return 0


def shown(value) -> str:
    """A value from a vocabulary file as one line of at most SHOWN_LIMIT characters (a hand-made file's
    newline cannot forge a line, nor its megabyte-long value flood the terminal)."""
    return one_line(shortened(value if isinstance(value, str) else str(value), SHOWN_LIMIT))


def fitted_on(vocabulary) -> str:
    """What the centres were learnt from, in words: the authors' release (known by its sha256), the
    datasets and features the metadata names, or that the file does not say (a bare tensor)."""
    from ..methods.anyloc_provenance import released_provenance
    from ..methods.anyloc_vocabulary import release

    meta = vocabulary.meta
    found = released_provenance(vocabulary)
    if found.get("source") == "released":
        r = release()
        datasets = ", ".join(found["datasets"]) or "not listed"
        return (f"the authors' released '{found['released_as']}' centres ({r['repository']} at {r['commit'][:12]}): "
                f"{r['backbone']} layer {r['layer']} {r['facet']} features of {datasets}")
    setting = " ".join(f"{key} {meta[key]}" for key in ("backbone", "layer", "facet") if key in meta)
    datasets = meta.get("fitted_on") or meta.get("datasets")  # dense-vlad's says it in words
    if isinstance(datasets, dict):
        datasets = ", ".join(f"{name} ({count} images)" for name, count in datasets.items())
    learnt = ", ".join(part for part in (
        " of ".join(part for part in (f"{setting} features" if setting else "", str(datasets or "")) if part),
        f"{meta['features_used']} of {meta['features_seen']} features sampled"
        if "features_used" in meta and "features_seen" in meta else "",
        f"imported from {meta['imported_from']}" if "imported_from" in meta else "",
    ) if part)
    if learnt:
        return shown(learnt)
    return "not recorded in the file (centres without metadata; sha256 " + found.get("sha256", "?")[:16] + ")"


def run_list(args) -> int:
    from ..aggregation.vocabulary import RELEASED_FILE, VOCABULARY_FILE, load_vocabulary, vocabularies_root

    resolve_locations(args)
    root = vocabularies_root(args.cache_dir)
    folders = sorted(folder for folder in root.glob("*/*") if folder.is_dir()) if root.is_dir() else []
    # both files of a folder: one's own beside the authors' is not the one a run reads there
    found = [(folder, folder / name) for folder in folders for name in (VOCABULARY_FILE, RELEASED_FILE)
             if (folder / name).is_file()]
    if not found:
        say(one_line(f"No vocabularies in {root}: `vprbench vocabulary fit`, `import` or `download` makes them."))
        return 0
    say(one_line(f"Vocabularies in {root} (setting/name: clusters x dims, fitted on):"))
    for folder, file in found:
        try:
            vocabulary = load_vocabulary(file)
        except VPRBenchError as error:  # one damaged file does not hide the others
            say(one_line(f"  {folder.parent.name}/{folder.name}: unusable: {error}"))
            continue
        both = sum(f == folder for f, _ in found) > 1
        say(f"  {shown(folder.parent.name)}/{shown(folder.name)}{f' ({file.name})' if both else ''}: {vocabulary.clusters} "
            f"x {vocabulary.dim}, {fitted_on(vocabulary)}{not_release(folder, vocabulary)}")
    return 0


def not_release(folder, vocabulary) -> str:
    """', NOT the authors' release ...' for centres cached under a name of the authors' release at their setting
    that are not it by sha256 (fitted or imported under that name); '' otherwise."""
    from ..aggregation.vocabulary import vocabulary_key
    from ..methods.anyloc_provenance import released_as
    from ..methods.anyloc_vocabulary import released_name, released_setting, released_sources

    names = {*released_sources(), *filter(None, map(released_name, released_sources()))}
    if folder.parent.name != vocabulary_key(*released_setting()) or folder.name not in names or released_as(vocabulary):
        return ""
    return (", NOT the authors' release (runs read their c_centers.pt first where it is here, `vprbench vocabulary "
            "download`; read without it, a run is recorded as not the release and gets a † row)")


def run_download(args) -> int:
    from ..methods.anyloc_vocabulary import fetch_released, release, released_name, released_sources

    resolve_locations(args)
    r = release()
    print(f"The authors' released centres ({r['backbone']} layer {r['layer']} {r['facet']}, {r['clusters']} clusters; "
          f"{r['repository']} at {r['commit'][:12]}):")
    for source in released_sources():
        path = fetch_released(source, args.cache_dir)
        print(f"  {source:<22} {released_name(source):<15} sha256 {r['sha256'][released_name(source)][:16]}  {path}")
    return 0


def run_domains(args) -> int:
    from ..methods.anyloc_vocabulary import domain_datasets, domain_image_size, domain_names

    height, width = domain_image_size()
    print(f"Domain vocabularies (images resized to {height}x{width}; dataset:stride):")
    for domain in domain_names():
        print(f"  {domain}: " + ", ".join(f"{name}:{stride}" for name, stride in domain_datasets(domain)))
    return 0
