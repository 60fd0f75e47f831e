"""Options shared by the commands, each meaning the same in every route.

Three kinds, kept apart because only the first two can change a result:
- method options (--backbone, --layer, ..., -o KEY=VALUE): part of the run's spec;
- spec options (--index, --index-option, --k, --store-dtype): part of the run's spec;
- run settings (--device, --batch-size, --workers, --search-memory, --lock-timeout, --download,
  --strict, --quiet): how it runs, never what it computes (`vprbench.spec.RunSettings`).
Locations (--data-dir, --cache-dir) default to $VPRBENCH_DATA / $VPRBENCH_CACHE here, and are
passed explicitly from here on. Nothing heavy is imported at module level: `vprbench --help`
answers at once.
"""
from __future__ import annotations

import argparse
import math
import os
import shlex
import tempfile
from pathlib import Path

from ..errors import VPRBenchError, name_roots, os_error_message
from ..paths import special_file

#: method options with a flag of their own (the rest go through -o KEY=VALUE)
METHOD_FLAGS = ("backbone", "weights", "layer", "facet", "aggregation", "clusters", "vocabulary", "resize", "pca_dim",
                "pca_on", "precision")
INDEXES = ("exact", "ivf-pq", "hnsw")
DEFAULT_LEASE_S = 120.0


def resolve_locations(args) -> None:
    """--data-dir / --cache-dir as given, else from the environment; error messages learn them. A
    cache folder that is a file is refused here, on every command (one that reads nothing from it
    would otherwise go on as if it were fine)."""
    from ..paths import CACHE_ENV, DATA_ENV, cache_root, environment_folder

    if hasattr(args, "data_dir"):  # where it came from, for messages about it
        args.data_dir_source = "--data-dir" if args.data_dir is not None else f"${DATA_ENV}"
        args.data_dir = environment_folder(args.data_dir, DATA_ENV, "--data-dir")
    if hasattr(args, "cache_dir"):
        source = "--cache-dir" if args.cache_dir is not None else f"${CACHE_ENV}"
        args.cache_dir = environment_folder(args.cache_dir, CACHE_ENV, "--cache-dir")
        if args.cache_dir is not None:
            cache_root(args.cache_dir, source)
    name_roots(cache_dir=getattr(args, "cache_dir", None), data_dir=getattr(args, "data_dir", None))


def refuse_unused(args, dest: str, why: str) -> None:
    """An option given that this route of the command does not use is refused, not ignored: the user
    meant it to matter. Called before `resolve_locations` (the environment's defaults are no option
    given). `why` completes "--flag VALUE is not used ...", e.g. "without --dataset"."""
    value = getattr(args, dest, None)
    if value is not None:  # quoted as a shell would need it: an empty value ('--cache-dir=') is seen as ''
        raise VPRBenchError(f"--{dest.replace('_', '-')} {shlex.quote(str(value))} is not used {why}: leave it out.")


class Unused(argparse.Action):
    """An option this command never uses: left out of --help, and refused by name when given."""

    def __call__(self, parser, namespace, values, option_string=None):
        parser.error(f"{option_string} is not used by '{parser.prog}': leave it out")


def add_location_options(parser: argparse.ArgumentParser, *, data: bool = True, cache: bool = True,
                         cache_help: str = "where descriptor stores, vocabularies and results live") -> None:
    """The folder options; one a command never uses is refused (ignored, it would look as if it mattered)."""
    parser.add_argument("--data-dir", **({} if data else {"action": Unused, "default": argparse.SUPPRESS}),
                        help="data root holding the datasets (default: $VPRBENCH_DATA or the user cache)"
                        if data else argparse.SUPPRESS)
    parser.add_argument("--cache-dir", **({} if cache else {"action": Unused, "default": argparse.SUPPRESS}),
                        help=f"{cache_help} (default: $VPRBENCH_CACHE or the user cache)" if cache else argparse.SUPPRESS)


# ---------------------------------------------------------------- method options
def add_method_options(parser: argparse.ArgumentParser, several: bool = False) -> None:
    if several:
        parser.add_argument("--method", required=True, nargs="+", help="method or preset names ('vprbench methods list')")
    else:
        parser.add_argument("--method", required=True, help="method or preset name ('vprbench methods list')")
    add_method_flags(parser)


def _helps(shown: bool):
    return (lambda text: text) if shown else (lambda text: argparse.SUPPRESS)


def add_method_flags(parser: argparse.ArgumentParser, shown: bool = True) -> None:
    """`shown=False`: accepted (so a command can refuse them by name) but left out of --help."""
    h = _helps(shown)
    group = parser.add_argument_group("method options (override the preset; a method rejects those it does not use)")
    group.add_argument("--backbone", help=h("backbone, e.g. dinov2_vitg14, dino_vits8, resnet101"))
    group.add_argument("--weights", help=h("local weights file in the official checkpoint format, or random (AnyLoc "
                       "backbones: a seeded random initialisation, a pipeline check)"))
    group.add_argument("--layer", type=int, help=h("0-based index of the block the features come from"))
    group.add_argument("--facet", help=h("query, key, value or token"))
    group.add_argument("--aggregation", help=h("gap, gmp, gem, vlad, vlad-soft-official, vlad-soft, cls"))  # = anyloc.AGGREGATIONS
    group.add_argument("--clusters", type=int, help=h("VLAD vocabulary size"))
    group.add_argument("--vocabulary", help=h("vocabulary name (map, indoor, urban, ...) or file (e.g. c_centers.pt)"))
    group.add_argument("--resize", type=int, nargs=2, metavar=("H", "W"), help=h("resize images to H x W"))
    group.add_argument("--pca-dim", type=int, help=h("PCA-whitening output dimension"))
    group.add_argument("--pca-on", help=h("what PCA-whitening is fitted on: database (the evaluated one, default) or "
                       "domain (its domain's databases stacked, as the AnyLoc authors' code)"))
    group.add_argument("--precision", choices=("fp32", "fp16", "bf16"), help=h("autocast precision on GPU (default fp32)"))
    group.add_argument("-o", "--option", action="append", default=[], metavar="KEY=VALUE",
                       help=h("any other method option (repeatable)"))


def _value(text: str):
    for cast in (int, float):
        try:
            value = cast(text)
        except ValueError:
            continue
        if isinstance(value, float) and not math.isfinite(value):
            return text  # 'nan', 'inf' stay words: the method's check names them
        return value
    return {"true": True, "false": False}.get(text.lower(), text)


def key_values(items: list[str], flag: str) -> dict:
    """['key=value', ...] -> {key: value}, values read as int, float or bool where they are one."""
    found = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise VPRBenchError(f"{flag} expects KEY=VALUE, got {item!r}")
        found[key.strip().replace("-", "_")] = _value(value.strip())
    return found


def method_options(args) -> dict:
    """The method options the user gave (None = use the preset's)."""
    from ..methods.checks import canonical

    options = {name: getattr(args, name, None) for name in METHOD_FLAGS}
    options["resize"] = list(args.resize) if getattr(args, "resize", None) else None
    for key, value in key_values(getattr(args, "option", []), "-o").items():
        if options.get(key) is not None and canonical(key, options[key]) != canonical(key, value):
            # else one of the two would be dropped, silently, and the run not be the one asked for
            flag, given = f"--{key.replace('_', '-')}", options[key]
            shown = " ".join(map(str, given)) if isinstance(given, list) else given
            raise VPRBenchError(f"{flag} {shown} and -o {key}={value} disagree; give {key} once.")
        options[key] = value
    return {k: v for k, v in options.items() if v is not None}


# ---------------------------------------------------------------- spec options
def add_spec_options(parser: argparse.ArgumentParser, shown: bool = True) -> None:
    """`shown=False`: as add_method_flags."""
    h = _helps(shown)
    group = parser.add_argument_group("what is computed besides the method (part of the run's identity)")
    group.add_argument("--k", nargs="+", help=h("K values for Recall@K (default 1 5 10 20)"))
    group.add_argument("--index", choices=INDEXES, default=None,
                       help=h("exact (default): streamed exact search; ivf-pq or hnsw: approximate faiss index, "
                            "shortlist re-scored exactly, recall loss against exact reported (its own leaderboard row)"))
    group.add_argument("--index-option", action="append", default=[], metavar="KEY=VALUE",
                       help=h("an approximate index's option, e.g. nprobe=64 (repeatable; docs/evaluation.md)"))
    group.add_argument("--store-dtype", choices=("float32", "float16"), default=None,
                       help=h("descriptor store precision; float16 halves the disk, reading gives float32 (default: float32)"))
    group = parser.add_argument_group("post-retrieval stages (part of the run's identity; docs/stages.md)")
    group.add_argument("--rerank", metavar="STAGE", help=h("re-rank the candidates: sift-ransac, aqe, dba or a plugin's"))
    group.add_argument("--rerank-k", type=int, metavar="K", help=h("how many candidates the re-ranker re-orders (default 100)"))
    group.add_argument("--rerank-option", action="append", default=[], metavar="KEY=VALUE",
                       help=h("a re-ranker's option, e.g. model=homography (repeatable)"))
    group.add_argument("--sequence", metavar="STAGE", help=h("sequence matching over the traverse (e.g. seqslam)"))
    group.add_argument("--sequence-length", type=int, metavar="N", help=h("frames in a sequence"))
    group.add_argument("--sequence-option", action="append", default=[], metavar="KEY=VALUE",
                       help=h("a sequence stage's option (repeatable)"))


def spec_overrides(args) -> dict:
    """What the spec options set, for every run of the command (None = the plan's or the default)."""
    from ..spec import check_ks

    ks = check_ks(args.k) if getattr(args, "k", None) else None
    return {"search": search_flags(args), "k": list(ks) if ks else None,
            "store_dtype": getattr(args, "store_dtype", None), "stages": stage_flags(args)}


def search_flags(args) -> dict | None:
    """--index and --index-option as a search table; None when neither is given. Without --index it names
    no index: a plan's own is kept (a single run's is exact)."""
    options = key_values(getattr(args, "index_option", []), "--index-option")
    if not getattr(args, "index", None) and not options:
        return None
    return {"options": options, **({"index": args.index} if args.index else {})}


def stage_flags(args) -> list[dict] | None:
    """--rerank / --sequence and their options as the spec's stage list, None when none. Sequence matching
    first: it matches against the whole database, so a re-ranker can only re-order what it found."""
    stages = []
    for kind, size, name in (("sequence", "sequence_length", "length"), ("rerank", "rerank_k", "k")):
        stage = getattr(args, kind, None)
        options = key_values(getattr(args, f"{kind}_option", None) or [], f"--{kind}-option")
        if "name" in options:  # it would replace the stage named, past the track check
            raise VPRBenchError(f"--{kind}-option name={options['name']} would replace the stage; give the stage "
                                f"with --{kind} STAGE.")
        if getattr(args, size, None) is not None:
            flag = f"--{size.replace('_', '-')}"
            if name in options and options[name] != getattr(args, size):
                raise VPRBenchError(f"{flag} {getattr(args, size)} and --{kind}-option {name}={options[name]} "
                                    f"disagree; give {name} once.")
            options[name] = getattr(args, size)
        if stage is None:
            if options:
                raise VPRBenchError(f"--{kind}-{'k' if kind == 'rerank' else 'length'} and --{kind}-option need "
                                    f"--{kind} STAGE (e.g. --{kind} {'sift-ransac' if kind == 'rerank' else 'seqslam'}).")
            continue
        from ..stages.registry import stage_entry

        rerank = stage_entry(stage).cls.track == "re-ranked"  # else the flag is ignored: it runs as its own kind
        if rerank != (kind == "rerank"):
            raise VPRBenchError(f"Stage {stage!r} is {'a re-ranker' if rerank else 'a sequence stage'}: give it with "
                                f"--{'rerank' if rerank else 'sequence'} {stage}, not --{kind}.")
        stages.append({"name": stage, **options})
    return stages or None


# ---------------------------------------------------------------- run settings
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


def path_argument(text: str) -> Path:
    """argparse type: a path; an empty one is refused (Path('') is the current folder, so an
    unset shell variable would write or read there)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"expected a path, got {text!r}")
    return Path(text)


def output_file(*suffixes: str):
    """argparse type: a file to write, checked before any work. Its folder must exist (a typo would
    otherwise create folders anywhere, found only once the work is done) and take a new file (a
    read-only disk or folder would otherwise fail the final write); `suffixes`, when given, are the
    endings it may have."""
    def parse(text: str) -> Path:
        path = path_argument(text)
        if suffixes and path.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"expected a {' or '.join(suffixes)} file, got {text}")
        folder = path.expanduser().parent
        try:
            if path.expanduser().is_dir():
                raise argparse.ArgumentTypeError(f"{text} is a folder: give a file name in it")
            if special_file(path.expanduser()):  # the final rename would put a file where the pipe or device was
                raise argparse.ArgumentTypeError(f"{text} is a named pipe, device or socket, not a file: give the "
                                                 "path of a file to write")
            if folder.exists() and not folder.is_dir():
                raise argparse.ArgumentTypeError(f"{folder} is a file, not a folder: check the path")
            if folder.is_dir():  # the file is renamed into it at the end: one made there now (unnamed on Linux)
                tempfile.TemporaryFile(dir=folder).close()
        except OSError as error:  # a name too long, a folder not readable, or not writable
            raise argparse.ArgumentTypeError(os_error_message(error, path).rstrip(".")) from None
        if not folder.is_dir():
            raise argparse.ArgumentTypeError(f"the folder {folder} does not exist: create it first or write elsewhere")
        return path
    return parse


def check_new_folder(path: Path, flag: str) -> None:
    """A folder a command writes into, made when missing: its parent must exist, as an output file's
    folder must (a typo would otherwise make a tree of folders anywhere)."""
    folder = path.expanduser()
    if not os.path.lexists(folder) and not os.path.lexists(folder.parent):  # a file there is told where it is made
        raise VPRBenchError(f"{flag} {folder}: the folder {folder.parent} does not exist: create it first or write "
                            "elsewhere.")


def add_run_options(parser: argparse.ArgumentParser, *, download: bool = True, quiet: bool = True,
                    strict: bool = True) -> None:
    """The run settings' flags; `strict` and `download` only for commands that load a dataset."""
    group = parser.add_argument_group("how it runs (never changes a result)")
    group.add_argument("--device", default="auto",
                       help="torch device: auto (cuda when available, else cpu), cpu, cuda, cuda:1 (default: auto)")
    group.add_argument("--batch-size", type=int, help="images per forward pass (>= 1)")
    group.add_argument("--workers", type=whole_number(0),
                       help="data-loader worker processes reading images, at most 1024 (default: 0 on cpu, up to 4 "
                             "on cuda)")
    group.add_argument("--search-memory", metavar="SIZE",
                       help="memory budget of search and PCA fitting, e.g. 1GB, 512MB, 4GiB (default 1.0 GB)")
    group.add_argument("--lock-timeout", type=float, metavar="SECONDS",
                       help="give up waiting for another run's store lock after this long (default: wait)")
    if strict:
        group.add_argument("--strict", action="store_true", help="fail when image counts differ from the manifest")
    if download:
        group.add_argument("--download", action="store_true",
                           help="fetch a missing dataset into --data-dir (without it, only the default data root is downloaded into)")
    if quiet:
        group.add_argument("--quiet", action="store_true",
                           help="no progress (without a terminal, progress is a line to stderr at most every 30 s)")


def add_sweep_options(parser: argparse.ArgumentParser) -> None:
    """--lease, checked with the run settings (sweep/claims.py: finite, at least 1 s)."""
    parser.add_argument("--lease", type=float, default=DEFAULT_LEASE_S, metavar="SECONDS",
                        help="a claim without heartbeat for this long belonged to a dead process and is taken over "
                             f"(default {DEFAULT_LEASE_S:g})")


def run_settings(args):
    """The run settings of the command line (locations resolved first), by flag or with -o."""
    from ..spec import RunSettings
    from ..sweep.claims import checked_lease

    if hasattr(args, "lease"):  # checked even when this run makes no claim (one evaluation)
        checked_lease(args.lease)
    if getattr(args, "download", False) and args.data_dir is not None:  # as `datasets download` checks it
        check_new_folder(Path(args.data_dir), args.data_dir_source)
    return RunSettings(cache_dir=args.cache_dir, data_dir=args.data_dir, **explicit_run_options(args),
                       download=True if getattr(args, "download", False) else None, strict=getattr(args, "strict", False))


def progress(args, stderr_is_rank_zero: bool = True):
    """The progress display this command shows (a terminal's bars, a log's lines, or nothing)."""
    from ..progress import Silent, progress_for

    return progress_for(quiet=getattr(args, "quiet", False)) if stderr_is_rank_zero else Silent()


def explicit_run_options(args) -> dict:
    """Run settings given on the command line, by flag or with -o (`-o workers=2`), over a plan
    entry's; a flag and -o giving one setting two values are refused, as method options are."""
    from ..row_sources import parse_memory
    from ..spec import split_run_settings

    given = split_run_settings(method_options(args))[1]
    device = getattr(args, "device", None)
    flags = {"device": None if device in (None, "auto") else device,  # '' is checked, not auto
             "batch_size": getattr(args, "batch_size", None), "workers": getattr(args, "workers", None),
             "memory_budget": getattr(args, "search_memory", None), "lock_timeout": getattr(args, "lock_timeout", None)}
    flags = {k: v for k, v in flags.items() if v is not None}
    for name in set(flags) & set(given):
        same = (parse_memory(flags[name]) == parse_memory(given[name]) if name == "memory_budget"  # 1GB = 1000MB
                else flags[name] == given[name] or str(flags[name]) == str(given[name]))
        if not same:  # else one is dropped, silently
            flag = {"memory_budget": "--search-memory"}.get(name, f"--{name.replace('_', '-')}")
            raise VPRBenchError(f"{flag} {flags[name]} and -o {name}={given[name]} disagree; give {name} once.")
    return {**given, **flags}
