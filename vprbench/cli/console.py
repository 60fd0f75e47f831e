"""Terminal output: every string from data prints as it is. Rich's markup and emoji codes are off
(a row `colorhist [bins=4]` keeps its brackets, a name `[link=javascript:...]x[/link]` or
`:pile_of_poo:` is not interpreted), and control characters are written out as escapes
(text.literal), so a name or path from a record or a dataset cannot drive the terminal."""
from __future__ import annotations

import codecs
import sys

from rich.console import Console
from rich.text import Text

from ..errors import ProblemList, VPRBenchError
from ..text import literal, one_line


class _Literal(Console):
    """A console for which every string is text: strings given to print, table cells and titles
    all pass through render_str."""

    def render_str(self, text: str, **options) -> Text:
        return super().render_str(literal(text), **options)


def console(stderr: bool = False) -> Console:
    return _Literal(stderr=stderr, markup=False, emoji=False)


def styled(text: str, style: str) -> Text:
    """A piece of text in a style (a Text is not a string: it is made literal here)."""
    return Text(literal(text), style=style)


def say(text: str, stderr: bool = False) -> None:
    """One plain line (or several) on stdout or stderr, made literal: for output meant for files and
    pipes as well (CSV, Markdown), which rich would wrap."""
    print(literal(text), file=sys.stderr if stderr else sys.stdout)


def print_error(message: str, lines: bool = False) -> None:
    """One line (a line break from a name or path written out), or a ProblemList's lines (`lines`)."""
    # soft wrap: no line breaks inserted, so paths in the message stay whole for copying
    console(stderr=True).print(styled("error:", "bold red"), message if lines else one_line(message), highlight=False,
                               soft_wrap=True)


def say_error(error: VPRBenchError) -> None:
    print_error(str(error), lines=isinstance(error, ProblemList))


def escape_unwritable() -> None:
    """On a terminal or file whose encoding cannot hold a character (an ASCII locale, a Windows code
    page), the character is written escaped (\\u2026), not a crash: tables and names from data are Unicode."""
    for stream in (sys.stdout, sys.stderr):
        utf = codecs.lookup(getattr(stream, "encoding", None) or "ascii").name.startswith("utf")
        if hasattr(stream, "reconfigure") and (getattr(stream, "errors", None) == "strict" or not utf):
            stream.reconfigure(errors="backslashreplace")
