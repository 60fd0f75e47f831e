"""One run, one specification: a flag given twice with different values is refused, not resolved.

argparse keeps a repeated flag's last value, so `--k 1 5 --k 10` would silently run K=[10] and
`-o cell=8 -o cell=4` cell 4. `Parser` (main.py) registers these actions for every command: a
single- or multi-valued flag may be given twice only with the same value; a repeatable KEY=VALUE
flag (-o, --index-option, ...) repeats for different keys, a key twice only with the same value.
Flags are tracked by dest, so two spellings of one flag (-o, --option) count as one.
"""
from __future__ import annotations

import argparse


def shown(values) -> str:
    return " ".join(map(str, values)) if isinstance(values, (list, tuple)) else str(values)


def _given(parser) -> dict:
    """dest -> what this parse has seen of it (reset for each parse by Parser.parse_known_args)."""
    if not hasattr(parser, "given_flags"):
        parser.given_flags = {}
    return parser.given_flags


class StoreOnce(argparse._StoreAction):
    """argparse's 'store', refusing a second, different value for the same flag."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = _given(parser)
        if option_string is not None and self.dest in given and given[self.dest][1] != values:
            first_flag, first = given[self.dest]
            flag = option_string if option_string == first_flag else f"{first_flag} / {option_string}"
            what = f"give it once, e.g. {option_string} {shown(_merged(first, values))}" \
                if self.nargs in ("+", "*") else "give it once, with the value you mean"
            # Parser.error: one line, exit 2, like argparse's own usage errors
            parser.error(f"{flag} given twice ({shown(first)}, then {shown(values)}): {what}")
        if option_string is not None:
            given[self.dest] = (option_string, values)
        super().__call__(parser, namespace, values, option_string)


def _merged(first: list, then: list) -> list:
    """Both lists in order, each value once: what a researcher typing the flag twice most likely meant."""
    merged = list(first)
    merged += [value for value in then if value not in merged]
    return merged


def _key(item: str):
    """KEY=VALUE's key as options.key_values reads it, and its value's text (compared as text: 'true'
    and '1' read as equal numbers); None for a malformed item (refused there, naming the flag)."""
    key, sep, value = item.partition("=")
    if not sep or not key.strip():
        return None, None
    return key.strip().replace("-", "_"), value.strip()


class AppendKeys(argparse._AppendAction):
    """argparse's 'append' for KEY=VALUE flags, refusing one key given twice with different values."""

    def __call__(self, parser, namespace, values, option_string=None):
        key, value = _key(values) if isinstance(values, str) else (None, None)
        seen = _given(parser).setdefault(self.dest, {})
        if key is not None and key in seen and seen[key][1] != value:
            parser.error(f"{option_string} {key} given twice ({seen[key][0].strip()}, then {values.strip()}): give "
                         f"each key once, with the value you mean")
        if key is not None and key not in seen:
            seen[key] = (values, value)
        super().__call__(parser, namespace, values, option_string)


def register(parser: argparse.ArgumentParser) -> None:
    """Make 'store' (argparse's default) and 'append' refuse repeats on this parser and its groups."""
    parser.register("action", None, StoreOnce)
    parser.register("action", "store", StoreOnce)
    parser.register("action", "append", AppendKeys)
