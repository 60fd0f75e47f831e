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
    group.add_argument("--device", default="auto",
                       help="torch device: auto (cuda when available, else cpu), cpu, cuda, cuda:1 (default: auto)")
    group.add_argument("--backbone", help="backbone, e.g. dinov2_vitg14, dino_vits8, resnet101")
    group.add_argument("--weights", help="local weights file in the official checkpoint format")
    group.add_argument("--layer", type=int, help="0-based index of the block the features come from")
    group.add_argument("--facet", help="query, key, value or token")
    group.add_argument("--aggregation", help="gap, gmp, gem, vlad, vlad-soft-official, vlad-soft")
    group.add_argument("--clusters", type=int, help="VLAD vocabulary size")
    group.add_argument("--vocabulary", help="vocabulary name (map, indoor, urban, ...) or file (e.g. c_centers.pt)")
    group.add_argument("--resize", type=int, nargs=2, metavar=("H", "W"), help="resize images to H x W")
    group.add_argument("--pca-dim", type=int, help="PCA-whitening output dimension")
    group.add_argument("--batch-size", type=int, help="images per forward pass (>= 1)")
    group.add_argument("--precision", choices=("fp32", "fp16", "bf16"), help="autocast precision on GPU (default fp32)")
    group.add_argument("-o", "--option", action="append", default=[], metavar="KEY=VALUE",
                       help="any other method option (repeatable)")


def whole_number(minimum: int):
    """argparse type: an integer >= minimum."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.__name__ = f"whole number >= {minimum}"
    return parse


def add_extraction_options(parser: argparse.ArgumentParser) -> None:
    """How descriptors are computed and kept (not part of the method: they never change a descriptor's value,
    except --store-dtype, which is part of the store key)."""
    group = parser.add_argument_group("extraction")
    group.add_argument("--workers", type=whole_number(0),
                       help="data-loader worker processes reading images (default: 0 on cpu, up to 4 on cuda)")
    group.add_argument("--store-dtype", choices=("float32", "float16"), default="float32",
                       help="descriptor store precision; float16 halves the disk, reading gives float32 (default: float32)")
    group.add_argument("--lock-timeout", type=float, metavar="SECONDS",
                       help="give up waiting for another run's store lock after this long (default: wait)")


def extraction_settings(args, device: str) -> dict:
    """Keyword arguments of evaluate / describe_splits from the extraction options."""
    from ..loader import default_workers

    workers = args.workers if args.workers is not None else default_workers(device)
    return {"workers": workers, "store_dtype": args.store_dtype, "lock_timeout": args.lock_timeout}


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
    from ..loader import resolve_device

    options["device"] = resolve_device(options["device"])
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
