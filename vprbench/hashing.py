"""The one rule that turns a value into a name: JSON with sorted keys and no spaces, sha256,
16 hex digits. Protocols, stores, claims, results and leaderboard rows are all named by it."""
from __future__ import annotations

import hashlib
import json
from typing import Any


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no spaces; tuples become lists. Anything that is not plain
    data (numbers, strings, bools, None, lists, dicts with string keys) is refused."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), allow_nan=False, default=_refuse)


def _refuse(value):
    raise TypeError(f"{type(value).__name__} {value!r} is not plain data (numbers, text, lists, tables)")


def canonical_hash(value: Any, length: int = 16) -> str:
    """sha256 of `canonical_json(value)`, hex, the first `length` digits."""
    if isinstance(length, bool) or not isinstance(length, int) or not 1 <= length <= 64:  # else '' or a silent cut
        raise ValueError(f"canonical_hash's length takes a whole number from 1 to 64 (hex digits); got {length!r}")
    return hashlib.sha256(canonical_json(value).encode()).hexdigest()[:length]


def exact_data(value: Any, owner: str, where: str = "") -> Any:
    """`value` as plain data that names it exactly: numpy numbers as numbers, paths as text, tuples
    as lists. What text would name inexactly is refused, naming `owner` ("Method 'x': fingerprint()")
    and the key: an array (its text is summarised and rounded, so two differ and share a key), a set
    (ordered differently in each process), an object (its text holds its address), NaN."""
    import math
    import os

    from .errors import VPRBenchError

    if isinstance(value, dict):
        for key in value:  # JSON makes 1 the text "1": {1: a, "1": b} would key as {"1": b}; a tuple no key at all
            if not isinstance(key, str):
                raise VPRBenchError(f"{owner} holds the key {key!r} ({type(key).__name__}) at {where or 'its top'}; "
                                    "give its keys as text.")
        return {key: exact_data(item, owner, f"{where}.{key}" if where else str(key)) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [exact_data(item, owner, f"{where}[{i}]") for i, item in enumerate(value)]
    if type(value).__module__ == "numpy" and getattr(value, "shape", None) == ():  # np.float32(0.5), np.int64(8)
        value = value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if type(value).__module__ == "torch" and type(value).__name__ in ("dtype", "device"):  # text names it exactly
        return str(value)
    if isinstance(value, float) and not math.isfinite(value):
        raise VPRBenchError(f"{owner} holds {value} at {where or 'its top'}; give a finite number.")
    if value is None or isinstance(value, (str, int, float)):
        return value
    raise VPRBenchError(f"{owner} holds a {type(value).__name__} at {where or 'its top'}, which is not plain data "
                        "(numbers, text, lists, tables) and would not name it exactly: give e.g. a list, or the "
                        "sha256 of an array's bytes.")
