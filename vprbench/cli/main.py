"""The `vprbench` command: a thin shell over the Python API."""
from __future__ import annotations

import argparse
import sys
import warnings

from .. import __version__
from ..errors import VPRBenchError
from . import datasets, evaluate, leaderboard, methods, reproduce, run, vocabulary


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vprbench", description="Benchmark suite for visual place recognition.")
    parser.add_argument("--version", action="version", version=f"vprbench {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (evaluate, run, reproduce, datasets, methods, vocabulary, leaderboard):
        module.add_parsers(commands)
    return parser


def format_warning(message, category, filename, lineno, line=None) -> str:
    """Warnings are for people: one line, no source location."""
    return f"warning: {message}\n"


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    warnings.formatwarning = format_warning
    try:
        return args.run(args)
    except VPRBenchError as error:
        from rich.console import Console

        Console(stderr=True).print(f"[bold red]error:[/] {error}", highlight=False, markup=True)
        return 1
    except KeyboardInterrupt:
        print("interrupted; finished descriptors are kept and the next run resumes", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
