"""Where vprbench keeps what it computes (descriptor stores, vocabularies, results, weights)."""
from __future__ import annotations

import os
from pathlib import Path

CACHE_ENV = "VPRBENCH_CACHE"


def cache_root(cache_dir: str | Path | None = None) -> Path:
    """--cache-dir, else $VPRBENCH_CACHE, else the user cache folder."""
    if cache_dir is None:
        cache_dir = os.environ.get(CACHE_ENV)
    if cache_dir is None:
        import pooch

        return Path(pooch.os_cache("vprbench"))
    return Path(cache_dir).expanduser()
