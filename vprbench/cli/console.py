"""Terminal output: rich with markup off, so names, paths and messages print exactly as they are
(a row `colorhist [bins=4]` or a method called `hog[x]` would otherwise lose their brackets)."""
from __future__ import annotations

from rich.console import Console
from rich.text import Text


def console(stderr: bool = False) -> Console:
    return Console(stderr=stderr, markup=False)


def styled(text: str, style: str) -> Text:
    """A piece of text in a style (markup being off)."""
    return Text(text, style=style)
