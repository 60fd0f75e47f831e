"""Counts and quantities in words: '1 frame', '0 frames', '2 queries', '25 metres'; text from data
made safe for a terminal."""
from __future__ import annotations

import re

#: plurals that are not the word + "s"
IRREGULAR = {"query": "queries"}


def plural(count, word: str) -> str:
    """'1 frame', '0 frames', '2.5 frames'; `word` is the singular."""
    shown = f"{count:g}" if isinstance(count, float) else str(count)
    return f"{shown} {word if shown == '1' else IRREGULAR.get(word, word + 's')}"


def percent(fraction: float | None) -> str:
    """A fraction (recall at 100 % precision) shown like Recall@K, in percent with one decimal."""
    return "–" if fraction is None else f"{100 * fraction:.1f}"


def quantity(value, unit: str | None) -> str:
    """A radius in its unit, named in the plural as stored ('frames', 'metres'): '1 frame', '25 metres';
    the value alone without a unit, '–' without a value."""
    if value is None:
        return "–"
    if not unit:
        return f"{value:g}" if isinstance(value, (int, float)) else str(value)
    return plural(value, unit[:-1] if unit.endswith("s") else unit)


#: characters a terminal acts on (escape sequences, bells, carriage returns, backspaces); tabs and
#: newlines are text
CONTROL = re.compile(r"[\x00-\x08\x0b-\x1f\x7f-\x9f]")


def literal(text) -> str:
    """Text from data as a terminal should show it: each control character written out as its
    escape ('\\x1b'), so a name or path holding one is seen, never acted on (a title set, a
    screen cleared, a line overwritten)."""
    return CONTROL.sub(lambda found: f"\\x{ord(found.group()):02x}", str(text))
