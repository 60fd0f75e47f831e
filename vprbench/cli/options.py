"""Options shared by several commands: data/cache locations and method knobs."""
from __future__ import annotations

import argparse
import os

from ..errors import VPRBenchError
from ..evaluation.metrics import DEFAULT_KS
from ..evaluation.search import INDEXES
from ..rows import DEFAULT_MEMORY_BUDGET, format_bytes, parse_memory


def add_location_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data-dir", help="data root holding the datasets (default: $VPRBENCH_DATA or the user cache)")
    parser.add_argument("--cache-dir", help="where descriptor stores, vocabularies and results live (default: $VPRBENCH_CACHE or the user cache)")


def add_download_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--download", action="store_true",
                        help="fetch a missing dataset into --data-dir (without it, only the default data root is downloaded into)")


def apply_locations(args) -> None:
    """Every part of vprbench (vocabularies fitted on other datasets, stores) then sees the same folders."""
    if getattr(args, "data_dir", None):
        os.environ["VPRBENCH_DATA"] = args.data_dir
    if getattr(args, "cache_dir", None):
        os.environ["VPRBENCH_CACHE"] = args.cache_dir


def add_method_options(parser: argparse.ArgumentParser, several: bool = False) -> None:
    if several:
        parser.add_argument("--method", required=True, nargs="+", help="method or preset names ('vprbench methods list')")
    else:
        parser.add_argument("--method", required=True, help="method or preset name ('vprbench methods list')")
    group = parser.add_argument_group("method options (override the preset; a method rejects those it does not use)")
    group.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda (default: cpu)")
    group.add_argument("--backbone", help="backbone, e.g. dinov2_vitg14, dino_vits8, resnet101")
    group.add_argument("--weights", help="local weights file in the official checkpoint format")
    group.add_argument("--layer", type=int, help="0-based index of the block the features come from")
    group.add_argument("--facet", help="query, key, value or token")
    group.add_argument("--aggregation", help="gap, gmp, gem, vlad, vlad-soft-official, vlad-soft")
    group.add_argument("--clusters", type=int, help="VLAD vocabulary size")
    group.add_argument("--vocabulary", help="vocabulary name (map, indoor, urban, ...) or file (e.g. c_centers.pt)")
    group.add_argument("--resize", type=int, nargs=2, metavar=("H", "W"), help="resize images to H x W")
    group.add_argument("--pca-dim", type=int, help="PCA-whitening output dimension")
    group.add_argument("--batch-size", type=int, help="images per forward pass")
    group.add_argument("--precision", choices=("fp32", "fp16", "bf16"), help="autocast precision on GPU (default fp32)")
    group.add_argument("-o", "--option", action="append", default=[], metavar="KEY=VALUE",
                       help="any other method option (repeatable)")


def _value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(text.lower(), text)


def method_options(args) -> dict:
    """The options the user gave; None means 'use the preset's'."""
    options = {name: getattr(args, name) for name in
               ("device", "backbone", "weights", "layer", "facet", "aggregation", "clusters", "vocabulary",
                "pca_dim", "batch_size", "precision")}
    options["resize"] = tuple(args.resize) if args.resize else None
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise VPRBenchError(f"-o expects KEY=VALUE, got {item!r}")
        options[key.strip().replace("-", "_")] = _value(value.strip())
    return options


def parse_ks(values) -> tuple[int, ...]:
    if not values:
        return DEFAULT_KS
    try:
        return tuple(int(v) for text in values for v in str(text).split(","))
    except ValueError:
        raise VPRBenchError(f"--k takes positive whole numbers, got {' '.join(map(str, values))}") from None


def add_search_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("search (docs/evaluation.md)")
    group.add_argument("--index", choices=INDEXES, default="exact",
                       help="exact (default): streamed exact search; ivf-pq or hnsw: approximate faiss index, "
                            "shortlist re-scored exactly, recall loss against exact reported")
    group.add_argument("--search-memory", metavar="SIZE",
                       help=f"memory budget of search and PCA fitting, e.g. 1GB, 512MB, 4GiB "
                            f"(default {format_bytes(DEFAULT_MEMORY_BUDGET)})")


def search_settings(args) -> dict:
    """Keyword options of `retrieve` (and `evaluate`) from the search options."""
    memory = DEFAULT_MEMORY_BUDGET if args.search_memory is None else parse_memory(args.search_memory)
    return {"memory_budget": memory, "index": args.index}
