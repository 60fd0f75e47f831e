"""`vprbench vocabulary`: fit, import, show and list VLAD vocabularies.

Wire into the main parser with `add_parser(subparsers)`; `run(args)` does the work.
Fitting needs a method whose `iter_patch_features(paths, resize)` yields each image's
(N, D) patch features as they enter VLAD (AnyLoc provides it).
"""
from __future__ import annotations

import argparse
from pathlib import Path

from ..aggregation import domain_datasets, domain_image_size, load_vocabulary
from ..aggregation.policies import (
    MAP_PREFIX, domain_names, fit_domain_vocabulary, fit_map_vocabulary, save_to_cache,
)
from ..aggregation.vocabulary import DEFAULT_BUDGET
from ..errors import VPRBenchError


def add_parser(subparsers) -> argparse.ArgumentParser:
    parser = subparsers.add_parser("vocabulary", help="fit, import, show and list VLAD vocabularies")
    commands = parser.add_subparsers(dest="vocabulary_command", required=True)

    fit = commands.add_parser("fit", help="fit a domain or map-specific vocabulary")
    which = fit.add_mutually_exclusive_group(required=True)
    which.add_argument("--domain", help=f"one of: {', '.join(domain_names())}")
    which.add_argument("--dataset", help="map-specific: the dataset's own database")
    fit.add_argument("--method", default="anyloc-vlad-dinov2", help="method preset giving the features")
    fit.add_argument("-o", "--option", action="append", default=[], metavar="KEY=VALUE", help="method option")
    fit.add_argument("--clusters", type=int, help="number of clusters (default: the method's)")
    fit.add_argument("--budget", type=int, default=DEFAULT_BUDGET, help="features kept by the seeded sampler")
    fit.add_argument("--exact", action="store_true", help="official fit on every patch (memory grows with data)")
    fit.add_argument("--seed", type=int, default=42)
    fit.add_argument("--output", type=Path, help="also write the vocabulary file here")

    imp = commands.add_parser("import", help="put a vocabulary file (e.g. the authors' c_centers.pt) in the cache")
    imp.add_argument("path", type=Path)
    imp.add_argument("--source", required=True, help="domain name or map-<dataset>")
    imp.add_argument("--backbone", default="dinov2_vitg14")
    imp.add_argument("--layer", type=int, default=31)
    imp.add_argument("--facet", default="value")

    show = commands.add_parser("show", help="print a vocabulary file's shape and metadata")
    show.add_argument("path", type=Path)

    commands.add_parser("domains", help="list the domain vocabularies and their datasets")
    return parser


def _method_options(pairs: list[str]) -> dict:
    options = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            raise VPRBenchError(f"Option {pair!r} is not KEY=VALUE.")
        options[key.strip()] = value
    return options


def _fit(args) -> None:
    from ..methods.registry import create_method

    options = _method_options(args.option)
    if args.clusters:
        options["clusters"] = args.clusters
    method = create_method(args.method, device=getattr(args, "device", None) or "cpu", **options)
    if not hasattr(method, "iter_patch_features"):
        raise VPRBenchError(f"Method {args.method!r} does not expose patch features, so it cannot fit a vocabulary.")
    clusters = int(method.clusters)
    setting = {"backbone": method.backbone, "layer": method.layer, "facet": method.facet}
    common = {"exact": args.exact, "budget": args.budget, "seed": args.seed, "meta": dict(setting)}
    data_dir = getattr(args, "data_dir", None)
    if args.domain:
        size = domain_image_size()
        vocabulary = fit_domain_vocabulary(
            args.domain, lambda paths: method.iter_patch_features(paths, resize=size), clusters,
            data_dir=data_dir, **common)
        source = args.domain
    else:
        vocabulary = fit_map_vocabulary(
            args.dataset, lambda paths: method.iter_patch_features(paths, resize=None), clusters,
            data_dir=data_dir, **common)
        source = f"{MAP_PREFIX}{args.dataset}"
    path = save_to_cache(vocabulary, source=source, **setting)
    print(f"Vocabulary {source}: {vocabulary.clusters} x {vocabulary.dim}, "
          f"{vocabulary.meta['features_used']} of {vocabulary.meta['features_seen']} features -> {path}")
    if args.output:
        print(f"Also written to {vocabulary.save(args.output)}")


def run(args) -> int:
    command = args.vocabulary_command
    if command == "fit":
        _fit(args)
    elif command == "import":
        vocabulary = load_vocabulary(args.path)
        vocabulary.meta["imported_from"] = vocabulary.meta.pop("path")
        path = save_to_cache(vocabulary, args.backbone, args.layer, args.facet, args.source)
        print(f"Imported {vocabulary.clusters} x {vocabulary.dim} centres as {args.source!r} -> {path}")
    elif command == "show":
        vocabulary = load_vocabulary(args.path)
        print(f"{vocabulary.meta['path']}: {vocabulary.clusters} clusters x {vocabulary.dim} dims")
        for key, value in sorted(vocabulary.meta.items()):
            print(f"  {key}: {value}")
    elif command == "domains":
        height, width = domain_image_size()
        print(f"Domain vocabularies (images resized to {height}x{width}; dataset:stride):")
        for domain in domain_names():
            print(f"  {domain}: " + ", ".join(f"{name}:{stride}" for name, stride in domain_datasets(domain)))
    return 0
