"""Checking method options when a method is created, so a bad value fails at once with a
message naming the method, the option and what it accepts (not later as a crash in OpenCV
or a NaN after a model has loaded).

Options arrive from presets and the Python API as any value, and from the command line's
`-o key=value` as str, int, float or bool; each check accepts the forms that mean the same
value ("8", 8 and 8.0 for a whole number; "4,6,8" or [4, 6, 8] for a list) and returns it
in one type.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

from ..errors import VPRBenchError
from ..text import shortened


def _bounds(minimum, maximum) -> str:
    if minimum is not None and maximum is not None:
        return f" from {minimum} to {maximum}"
    if minimum is not None:
        return f" >= {minimum}"
    return f" <= {maximum}" if maximum is not None else ""


def whole(method: str, option: str, value, minimum: int | None = 1, maximum: int | None = None, what: str = "") -> int:
    """An int within [minimum, maximum]."""
    number = None
    if not isinstance(value, bool):
        try:
            number = float(value) if isinstance(value, (str, float)) else int(value)
        except (TypeError, ValueError, OverflowError):
            number = None
    if number is None or not math.isfinite(number) or number != int(number) or \
            (minimum is not None and number < minimum) or (maximum is not None and number > maximum):
        raise VPRBenchError(f"{method}: option {option} takes a whole number{_bounds(minimum, maximum)}"
                            f"{f' ({what})' if what else ''}; got {shortened(repr(value))}.")
    return int(number)


def number(method: str, option: str, value, minimum: float | None = None, above: float | None = None, what: str = "") -> float:
    """A finite float >= minimum (or > above)."""
    result = None
    if not isinstance(value, bool):
        try:
            result = float(value)
        except (TypeError, ValueError, OverflowError):
            result = None
    if result is None or not math.isfinite(result) or (minimum is not None and result < minimum) or \
            (above is not None and result <= above):
        bound = f" > {above:g}" if above is not None else (f" >= {minimum:g}" if minimum is not None else "")
        raise VPRBenchError(f"{method}: option {option} takes a finite number{bound}"
                            f"{f' ({what})' if what else ''}; got {shortened(repr(value))}.")
    return result


def wholes(method: str, option: str, value, minimum: int | None = 1, what: str = "") -> tuple[int, ...]:
    """A non-empty tuple of whole numbers, from one number, "4,6,8" or a sequence."""
    items = value.replace(" ", "").split(",") if isinstance(value, str) else value
    if not isinstance(items, Sequence) or isinstance(items, str):
        items = [items]
    if not items or any(isinstance(v, str) and not v for v in items):
        raise VPRBenchError(f"{method}: option {option} takes one or more whole numbers{_bounds(minimum, None)}, "
                            f"e.g. 4,6,8{f' ({what})' if what else ''}; got {shortened(repr(value))}.")
    try:
        return tuple(whole(method, option, v, minimum, what=what) for v in items)
    except VPRBenchError:
        raise VPRBenchError(f"{method}: option {option} takes one or more whole numbers{_bounds(minimum, None)}, "
                            f"e.g. 4,6,8{f' ({what})' if what else ''}; got {shortened(repr(value))}.") from None


def flag(method: str, option: str, value, none: str = "") -> bool | None:
    """True, False (or None when `none` says what it means): a str such as 'no' is truthy, so it
    is refused rather than read as True."""
    if isinstance(value, bool) or value is None and none:
        return value
    allowed = f"True, False or None ({none})" if none else "True or False"
    raise VPRBenchError(f"{method}: option {option} takes {allowed}; got {shortened(repr(value))}.")


def choice(method: str, option: str, value, choices: Sequence[str]) -> str:
    """One of `choices` (exactly)."""
    if not isinstance(value, str) or value not in choices:
        raise VPRBenchError(f"{method}: option {option} takes one of {', '.join(choices)}; got {shortened(repr(value))}.")
    return value


def text(method: str, option: str, value, what: str = "") -> str:
    """A non-empty string (a name or a path)."""
    if not isinstance(value, str) or not value.strip():
        raise VPRBenchError(f"{method}: option {option} takes a non-empty text{f' ({what})' if what else ''}; got {shortened(repr(value))}.")
    return value


def device(method: str, value) -> str:
    """A torch device name such as cpu, cuda or cuda:1, whose kind exists on this machine."""
    import torch

    try:
        chosen = torch.device(text(method, "device", value, "e.g. cpu or cuda"))
    except (RuntimeError, TypeError):
        raise VPRBenchError(f"{method}: option device takes a torch device such as cpu, cuda or cuda:1; got {shortened(repr(value))}.") from None
    if chosen.type == "cuda" and not torch.cuda.is_available():
        raise VPRBenchError(f"{method}: device {value!r} was asked for but no CUDA GPU is available; use --device cpu.")
    if chosen.type == "meta":  # tensors without data: every descriptor would be made of nothing
        raise VPRBenchError(f"{method}: device {value!r} holds no data, so it computes nothing; use --device cpu or cuda.")
    if chosen.type not in ("cpu", "cuda"):  # mps, xpu, ...: torch.device takes the name whether or not it is there
        try:
            torch.empty(0, device=chosen)
        except (RuntimeError, AssertionError):
            raise VPRBenchError(f"{method}: device {value!r} was asked for but this machine's PyTorch cannot use it; "
                                "use --device cpu.") from None
    return str(chosen)


def canonical(name: str, value):
    """One form for the ways of writing one option value, so one computation has one identity (a
    spec, a store, a leaderboard row): a whole float is an int (3.0 is 3), and `resize` is
    [H, W] however it was written (`-o resize=64,64`, '64x64', `--resize 64 64`, (64, 64)) or
    'native'; a path (`weights=Path(...)`) is its text, as on the command line. A value the method
    will refuse is left as it is, for the method to name."""
    import os

    if isinstance(value, os.PathLike):
        value = os.fspath(value)

    def whole(item):
        if isinstance(item, float) and item.is_integer():
            return int(item)
        if isinstance(item, (list, tuple)):
            return [whole(i) for i in item]
        return {k: whole(v) for k, v in item.items()} if isinstance(item, dict) else item

    value = whole(value)
    if name == "resize":
        from ..features.resize import parse_size

        try:
            size = parse_size(value)
        except VPRBenchError:
            return value
        return list(size) if size else "native"
    return value


def plain_options(method: str, options: dict) -> dict:
    """`options` as plain data (tuples as lists), or one line naming the method: an object, a set or
    NaN would not name the run exactly (refused when the method is created and in a spec alike)."""
    import json

    from ..hashing import canonical_json

    try:
        return json.loads(canonical_json(options))
    except (TypeError, ValueError) as error:
        raise VPRBenchError(f"Method {method!r}: an option is not plain data ({error}).") from None
