"""Long texts said once below a table: a cell carries "[1]", the text follows the table, plain and
wrapped at the terminal's width (a paragraph folded into a narrow column is unreadable and, one per
row, repeats the same instructions)."""
from __future__ import annotations

from rich.console import Group
from rich.text import Text

from .text import literal

#: a cell text longer than this goes into a note
SHORT = 40


class Notes:
    def __init__(self) -> None:
        self.numbers: dict[str, int] = {}

    def refer(self, text: str) -> str:
        """'[n]' for text, the same n for the same text."""
        return f"[{self.numbers.setdefault(text, len(self.numbers) + 1)}]"

    def short(self, text: str) -> str:
        """text itself when short, else a reference to it."""
        return text if len(text) <= SHORT else self.refer(text)

    def below(self, table) -> Group:
        """The table followed by its notes."""
        return Group(table, *(Text(literal(f"[{n}] {text}")) for text, n in self.numbers.items()))
