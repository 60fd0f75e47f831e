"""The `vprbench` command: a thin shell over the Python API."""
from __future__ import annotations

import argparse
import errno
import os
import sys
import warnings

from .. import __version__
from ..distributed import not_first_of_node, said_elsewhere, torchrun_rank
from ..errors import KEPT, ShardWarning, VPRBenchError, keeping, os_error_message
from . import datasets, evaluate, leaderboard, methods, reproduce, repeats, results, run, stages, vocabulary
from ..text import one_line
from .console import escape_unwritable, print_error, say_error


class Parser(argparse.ArgumentParser):
    """A usage error is one line like every other error; the whole usage is one --help away. Each
    subcommand's parser is of this class too (argparse makes them like their parent). A flag given
    twice with different values is refused (repeats.py), on every command."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        repeats.register(self)

    def parse_known_args(self, args=None, namespace=None):
        self.given_flags = {}  # what this parse has seen, for repeats.py
        Parser.innermost = self.prog  # a subcommand's parse comes after its parent's: the last is the deepest
        return super().parse_known_args(args, namespace)

    def parse_args(self, args=None, namespace=None):
        """As argparse's, but a flag no parser knows points at the help of the subcommand it was given to."""
        parsed, unknown = self.parse_known_args(args, namespace)
        if unknown:
            print_error(f"unrecognized arguments: {' '.join(unknown)}; see '{Parser.innermost} --help'")
            sys.exit(2)
        return parsed

    def error(self, message: str):
        print_error(f"{message}; see '{self.prog} --help'")
        sys.exit(2)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="vprbench", description="Benchmark suite for visual place recognition.")
    parser.add_argument("--version", action="version", version=f"vprbench {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in (evaluate, run, reproduce, datasets, methods, stages, vocabulary, leaderboard, results):
        module.add_parsers(commands)
    return parser


def warning_format():
    """Warnings are for people: one line, no source location, each text once per command (a
    dataset read for the run's identity and again for the run would otherwise say it twice) and,
    under torchrun, once per node: by its first rank, or by the rank it is about (`ShardWarning`)."""
    shown = set()

    def format_warning(message, category, filename, lineno, line=None) -> str:
        own = issubclass(category, ShardWarning)
        if not own and not_first_of_node():
            return ""
        rank = torchrun_rank() if own else None
        text = f"warning{'' if rank is None else f' (rank {rank})'}: {one_line(message)}\n"
        if text in shown:
            return ""
        shown.add(text)
        return text
    return format_warning


def kept(after: str = "") -> str:
    """'; finished descriptors are kept<after>' for a command that keeps its work, '' for one that keeps none."""
    return f"; {KEPT['what']} are kept{after}" if KEPT["what"] else ""


def out_of_memory(error: BaseException) -> str:
    found = str(error).strip().splitlines()
    return (f"Out of memory ({found[-1] if found else type(error).__name__}). Lower --batch-size or the image size "
            f"(--resize, a stage's resize), or run on a machine with more memory{kept()}.")


def main(argv=None) -> int:
    escape_unwritable()
    args = build_parser().parse_args(argv)
    warnings.formatwarning = warning_format()
    with keeping(getattr(args, "kept", None)):  # a command that resumes declares what it keeps (set_defaults)
        return _run(args)


def _run(args) -> int:
    try:
        return args.run(args)
    except VPRBenchError as error:
        if not said_elsewhere(error):  # under torchrun, one rank says what every rank met
            say_error(error)
        return 1
    except BrokenPipeError:  # output piped into a reader that stopped (| head): end quietly, as other tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as error:  # permissions, full or read-only disks, lock timeouts: say which path and what to do
        print_error(os_error_message(error))
        return 1
    except MemoryError as error:
        print_error(out_of_memory(error))
        return 1
    except RuntimeError as error:
        if "can't allocate memory" in str(error) or "out of memory" in str(error):  # torch's CPU and GPU allocators
            print_error(out_of_memory(error))
            return 1
        if str(error).startswith("Symlink loop from "):  # Path.resolve on a link loop, before Python 3.13
            looped = str(error).removeprefix("Symlink loop from ").strip("'")
            print_error(os_error_message(OSError(errno.ELOOP, os.strerror(errno.ELOOP), looped)))
            return 1
        if "home directory" not in str(error):
            raise
        # pathlib on '~name/...' for a user this machine does not know, from any path option
        print_error("A path starting with ~NAME names the home folder of a user this machine does not know: give "
                    "the path in full, or ~/... for your own home folder.")
        return 1
    except KeyboardInterrupt:
        print(f"interrupted{kept(' and the next run resumes')}", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
