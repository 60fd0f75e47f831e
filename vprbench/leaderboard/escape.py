"""Text from data on pages: what a published page may show of it, and the one escape every page
writer uses.

A page shows files and folders by name, never by the absolute path they had on the machine that
ran or published (a vocabulary folder in a row's label, a vocabulary file in a run's provenance, the
cache folder of a run left out): `public` cuts every absolute path in a text (and one
starting with ./, ../ or ~/) to its last name. The
board's labels, weights and reasons (cells.py), every Markdown string (`text`) and the downloads
(`public_data`) go through it. Every CSV the project writes goes through `to_csv`, so no cell
from data runs as a formula in a spreadsheet.
"""
from __future__ import annotations

import re

from ..text import literal

#: a path of the local machine: POSIX with two names or more ('/a/b'; one, '/b', is more often
#: something else, such as Rich's '[/b]') or from a start ('~/a', './a', '../a'), not inside a URL
#: or a fraction, but after a label's colon ('weights:/a/b'); or a Windows drive path ('C:\\a\\b').
#: Names end at white space and at the characters that close or separate them in text ('|',
#: brackets, quotes, ',', ';').
_NAME = r"[^\s/\\|\[\]()<>'\",;]+"
_ABSOLUTE = re.compile(rf"(?<![\w.~/\\-])(?:(?:~|\.\.?)(?:/{_NAME})+|(?:/{_NAME}){{2,}})/?|\b[A-Za-z]:\\(?:{_NAME}\\?)+")


#: a value that is one path as a whole ('/a/b', '~/a'): cut to its last name whatever it holds, as
#: `_ABSOLUTE`'s names end at a blank ('/home/ann lee/my data/own' was shown as 'ann lee/my data/own')
_ONE_PATH = re.compile(r"(?:~|\.\.?)?/[^/]+(?:/[^/]+)+/?|~/[^/]+/?", re.S)


def public(value) -> str:
    """`value` as text with each absolute path cut to its last name:
    'dense-vlad [vocabulary=/home/me/images/tokyo]' -> 'dense-vlad [vocabulary=tokyo]'; a value that is
    one path as a whole (a dataset's folder) whatever its names hold."""
    value = str(value)
    if _ONE_PATH.fullmatch(value):
        return value.rstrip("/").rpartition("/")[2]
    return _ABSOLUTE.sub(lambda found: re.split(r"[/\\]", found.group().rstrip("/\\"))[-1], value)


def public_data(value):
    """A record or download entry with `public` applied to every string in it (keys included)."""
    if isinstance(value, str):
        return public(value)
    if isinstance(value, dict):
        return {public(k) if isinstance(k, str) else k: public_data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [public_data(v) for v in value]
    return value


#: each character from data that Markdown (or HTML) would act on, as its character reference: '&',
#: '<', '>' and quotes as HTML; '|' (a cell break), '`' (a code span with one further along the row),
#: '*' and '_' (emphasis: '_x_', '__x__'; an '_' between two letters or digits stays, as in 'pca_dim':
#: it never starts or ends one), '#' (a heading's closing hashes: 'c#' read as 'c'); and
#: a backslash that Markdown reads as an escape, before a character it escapes or last (before the
#: page's own ']' or '|'): one from data would cancel a backslash escape or escape the bracket that
#: ends a link's text. One written out by `literal`, '\\x1b', stays as it is. One pass, so no
#: reference is escaped again.
_REFERENCES = {"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#x27;", "|": "&#124;", "`": "&#96;",
               "*": "&#42;", "_": "&#95;", "#": "&#35;", "\\": "&#92;"}
_MARKUP = re.compile(r"\\(?=[\\`*_{}\[\]()>#+\-.!|]|$)|[&<>\"'|`*#]|(?<![^\W_])_|_(?![^\W_])")


def text(value) -> str:
    """Text from data or records (names, labels, paths, reasons) as plain text in Markdown: no
    HTML element, no link or image, no emphasis, no table cell break can come from it, no absolute
    path. Each character of `_REFERENCES` is written as its character reference, a square bracket
    without its pair too (a lone bracket would end or open a link's text early: the link lost, the
    site's navigation unbuilt), and a line break of either kind as a space (a line of its own could
    define a link); other control characters are written out as their escapes ('\\x1b'), as on the
    terminal."""
    flat = public(value).replace("\r", " ").replace("\n", " ")
    escaped = _MARKUP.sub(lambda found: _REFERENCES[found.group()], literal(flat))
    return _paired_brackets(escaped).replace("](", "]\\(")


def code(value) -> str:
    """`text(value)` set as code: an HTML <code> element, not a Markdown code span, in which the
    character references of `text` would show as written ('&lt;' for '<')."""
    return f"<code>{text(value)}</code>"


def _paired_brackets(value: str) -> str:
    """`value` with each '[' or ']' that has no pair written as a character reference: paired ones
    read as written ('hog [note=x]') and nest inside a link's text."""
    opened, lone = [], set()
    for at, char in enumerate(value):
        if char == "[":
            opened.append(at)
        elif char == "]":
            if opened:
                opened.pop()
            else:
                lone.add(at)
    lone.update(opened)
    return "".join({"[": "&#91;", "]": "&#93;"}[c] if at in lone else c for at, c in enumerate(value))


#: how a cell that a spreadsheet runs as a formula begins (tab and carriage return are dropped
#: before it reads the rest)
FORMULA_START = ("=", "+", "-", "@", "\t", "\r")


def csv_cell(value):
    """A CSV cell: text beginning like a formula gets a leading quote, which spreadsheets read as
    'this is text'; numbers (negative ones too) and other values stay as they are. A lone '-' (an
    empty cell of the grid) is no formula."""
    if isinstance(value, str) and value.startswith(FORMULA_START) and value != "-":
        return "'" + value
    return value


def to_csv(frame, path=None, **options):
    """`frame.to_csv(path, **options)` with every cell, row name and column name through `csv_cell`:
    the one CSV writer of the project (the site's downloads, `vprbench leaderboard --format csv`).
    Lines end in CR LF (RFC 4180), so a cell holding a line break of either kind is quoted whole: a
    bare carriage return would otherwise end the row in a spreadsheet and start a cell after the guard."""
    options.setdefault("lineterminator", "\r\n")
    return frame.map(csv_cell).rename(index=csv_cell, columns=csv_cell).to_csv(path, **options)
