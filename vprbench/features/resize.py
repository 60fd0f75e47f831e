"""The one resize parser (every method's `resize` option) and AnyLoc's per-dataset sizes.

No torch here: baselines and the command line parse sizes without loading a network library.
"""
from __future__ import annotations

from ..errors import VPRBenchError

#: AnyLoc's per-dataset resize (height, width) before the crop; datasets not listed keep
#: their native size (Oxford, Gardens Point, Hawkins, Laurel Caverns, Nardo-Air, VP-Air).
#: Keys are vprbench dataset names; aliases map the other common spellings.
DATASET_RESIZE: dict[str, tuple[int, int]] = {
    "pitts30k": (480, 640),
    "st-lucia": (480, 640),
    "17places": (480, 640),
    "baidu-mall": (480, 640),
    "mid-atlantic-ridge": (405, 720),
}
_ALIASES = {
    "pitts30k-test": "pitts30k", "pittsburgh30k": "pitts30k", "pitts-30k": "pitts30k",
    "stlucia": "st-lucia", "st_lucia": "st-lucia",
    "17-places": "17places", "seventeen-places": "17places",
    "baidu": "baidu-mall", "baidu_mall": "baidu-mall", "baidumall": "baidu-mall",
    "mid-atlantic": "mid-atlantic-ridge", "eiffel": "mid-atlantic-ridge",
}


def dataset_resize(dataset: str | None) -> tuple[int, int] | None:
    """AnyLoc's resize for `dataset` (None = native size)."""
    if not dataset:
        return None
    key = dataset.strip().lower()
    return DATASET_RESIZE.get(_ALIASES.get(key, key))


def asks_native(size) -> bool:
    """`resize = "native"` written out: the image's own size, also where a policy would resize (AnyLoc
    on Pitts-30k); None leaves the choice to the policy."""
    return isinstance(size, str) and size.strip().lower() in ("", "none", "native")


def parse_size(size, name: str = "resize") -> tuple[int, int] | None:
    """(H, W) from a (H, W) pair, "HxW" / "H,W", one number for a square, or None / "native"."""
    if size is None or asks_native(size):
        return None
    if isinstance(size, str):
        parts = [p.strip() for p in size.lower().replace("x", ",").split(",")]  # '10x' is no size, nor 10x10
    elif isinstance(size, int) and not isinstance(size, bool):
        parts = [size]
    else:
        try:
            parts = list(size)
        except TypeError:
            parts = [size]
    if len(parts) == 1:
        parts = parts * 2
    try:
        if len(parts) != 2 or any(isinstance(p, bool) or (isinstance(p, float) and p != int(p)) for p in parts):
            raise ValueError
        h, w = (int(p) for p in parts)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an infinite size
        raise VPRBenchError(f"Option {name} takes HEIGHT WIDTH (e.g. 480x640, or one number for a square), "
                            f"got {size!r}.") from None
    if h <= 0 or w <= 0:
        raise VPRBenchError(f"Option {name} must be positive, got {h}x{w}.")
    from ..images import check_decode_budget  # images are resized to this: the same bound as decoding

    check_decode_budget(w, h, f"Option {name} {h}x{w}", advice="Choose a smaller size.")
    return h, w
