"""Counts and quantities in words: '1 frame', '0 frames', '2 queries', '25 metres'; text from data
made safe for a terminal. It imports nothing of vprbench: errors' messages are written with it."""
from __future__ import annotations

import re
import reprlib

#: plurals that are not the word + "s"
IRREGULAR = {"query": "queries"}


def plural(count, word: str) -> str:
    """'1 frame', '0 frames', '2.5 frames'; `word` is the singular."""
    shown = f"{count:g}" if isinstance(count, float) else str(count)
    return f"{shown} {word if shown == '1' else IRREGULAR.get(word, word + 's')}"


def recall_text(value: float | None) -> str:
    """A recall in percent (or an interval's end) as the tables, pages and `results` commands show it:
    one decimal, '–' without a value. One rounding everywhere: a verify line's 48.65
    beside the leaderboard's 48.6 read as a wrong rounding of one number."""
    return "–" if value is None or value != value else f"{value:.1f}"  # value != value: NaN


def percent(fraction: float | None) -> str:
    """A fraction (recall at 100 % precision) shown like Recall@K, in percent with one decimal. The
    fraction is kept to 8 decimals (metrics.PR_DECIMALS), so its percent has 6: rounded there, as a
    recall is kept, before it is shown (100 x 0.2875 is 28.749999999999996, which showed 28.7 where
    a recall of 23 / 80 shows 28.8)."""
    return "–" if fraction is None else f"{round(100 * fraction, 6):.1f}"


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


#: characters that show nothing yet change what is shown: bidi controls (which reverse the text
#: after them: a name's cell, a terminal's line of numbers) and zero-width ones (two names that
#: read alike, 'hog' and 'h\u200bog')
INVISIBLE = re.compile("[\u061c\u200b-\u200f\u202a-\u202e\u2060-\u2064\u2066-\u2069\ufeff]")
#: lone surrogates: the bytes of a name in another encoding as Python reads them (a command-line
#: argument, a folder), which no UTF-8 terminal or file can take
UNWRITABLE = re.compile("[\ud800-\udfff]")


def literal(text) -> str:
    """Text from data as a terminal should show it: each control character written out as its
    escape ('\\x1b'), so a name or path holding one is seen, never acted on (a title set, a
    screen cleared, a line overwritten); each INVISIBLE and UNWRITABLE character too ('\\u202e',
    '\\udcff'), so it is seen and can be written."""
    shown = CONTROL.sub(lambda found: f"\\x{ord(found.group()):02x}", str(text))
    for hidden in (INVISIBLE, UNWRITABLE):
        shown = hidden.sub(lambda found: f"\\u{ord(found.group()):04x}", shown)
    return shown


def one_line(text) -> str:
    """`literal`, and line breaks written out too ('\\n'): a name or path holding one cannot split
    a message into lines (or forge a line of its own)."""
    return literal(text).replace("\n", "\\n")


def first_clause(message: str) -> str:
    """A message's first clause, up to its first ': ' (what is wrong, not the how-to after it), without
    a parenthesis that cut leaves open ('... does not exist (closest existing folder')."""
    clause = str(message).split(": ")[0]
    while clause.count("(") > clause.count(")"):
        clause = clause[:clause.rindex("(")].rstrip()
    return clause.rstrip(".")  # after the cut: a sentence's own period stood before its parenthesis


def shortened(value, limit: int = 80) -> str:
    """`value` as a message shows it, at most `limit` characters (cut with '...'): a hand-edited
    file's megabyte-long value, or a client's paragraph, stays one readable line."""
    shown = value if isinstance(value, str) else reprlib.repr(value)
    return shown if len(shown) <= limit else shown[:limit - 3] + "..."
