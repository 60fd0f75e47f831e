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
    return hashlib.sha256(canonical_json(value).encode()).hexdigest()[:length]
