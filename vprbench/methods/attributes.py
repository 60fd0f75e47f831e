"""The attributes vprbench reads off a method object (needs_fit, compare, batch_size, device, cache_dir) and
those it sets on it (name, options, settings, batch_size), in one place: a plugin's property that raises, or a
value of another type ('yes' read as True, batch_size 2.5), is one line naming the method, the attribute and
what to do, before any image is described, not a traceback from wherever vprbench first reads it."""
from __future__ import annotations

import json
import os
import sys

import numpy as np

from ..errors import VPRBenchError
from ..hashing import exact_data
from ..loader import plugin_part
from ..registration import source_of

#: far above any real batch; the data loader crashes on one beyond sys.maxsize
MAX_BATCH_SIZE = 2**31 - 1
#: how two descriptors are compared: inner product of unit rows, or the mean absolute difference (sad)
COMPARES = ("cosine", "mean-absolute-difference")
#: read with a default (`getattr(method, "device", ...)`): a method need not have them
OPTIONAL = ("device", "cache_dir")


def _is_device(value) -> bool:
    torch = sys.modules.get("torch")  # a torch.device exists only once torch is imported
    return value is None or isinstance(value, str) and bool(value) or torch is not None and isinstance(value, torch.device)


def _is_batch_size(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, int) and 1 <= value <= MAX_BATCH_SIZE


def _rules() -> dict:
    """attribute -> (accepts(value), what it must be)."""
    return {
        "needs_fit": (lambda v: isinstance(v, (bool, np.bool_)), "True or False"),
        "compare": (lambda v: isinstance(v, str) and v in COMPARES, f"one of {', '.join(COMPARES)}"),
        "batch_size": (_is_batch_size, f"a whole number >= 1 (at most {MAX_BATCH_SIZE})"),
        "device": (_is_device, "a device name such as 'cpu' or 'cuda' (text or a torch.device), or None"),
        "cache_dir": (lambda v: v is None or isinstance(v, (str, os.PathLike)), "a folder (text or a path), or None"),
    }


def check_attributes(method, name: str | None = None, source: str | None = None) -> None:
    """Every attribute vprbench reads off `method` (created as `name`, registered by `source`), read once
    (a plugin's property that raises is `plugin_part`'s one line) and of the type its readers take."""
    name = method.name if name is None else name
    source = source or source_of(type(method))
    for attribute, (accepts, what) in _rules().items():
        with plugin_part(method, attribute, f"Method {name!r}", attribute=True):
            value = getattr(method, attribute, None) if attribute in OPTIONAL else getattr(method, attribute)
        if not accepts(value):
            hint = "fix the plugin, or pass --batch-size" if attribute == "batch_size" else "fix the plugin"
            raise VPRBenchError(f"Method {name!r} ({source}) has {attribute} {value!r}; it must be {what} ({hint}).")


#: where create_method keeps the method's fingerprint as made (objects.py refuses one changed since)
MADE_FINGERPRINT = "_made_fingerprint"


def own_fingerprint(method) -> dict:
    """`method.fingerprint()` as plain data, as the store keys it: what a plugin's raises, or a value that
    is no dict or names itself inexactly (an array, a set), is one line naming the method."""
    with plugin_part(method, "fingerprint"):
        own = method.fingerprint()
    if not isinstance(own, dict):
        raise VPRBenchError(f"Method {method.name!r}: fingerprint() must return a dict naming what changes its "
                            f"descriptors, got {type(own).__name__}.")
    own = exact_data(own, f"Method {method.name!r}: fingerprint()")  # as text, two arrays could share one key
    return json.loads(json.dumps(own, default=str))


def stamp_fingerprint(method, name: str, source: str) -> None:
    """Keep the fingerprint `method` has now, as vprbench made it (created, or told its dataset), to refuse
    it later if changed by hand: `m.size = 4` would be evaluated and stored under the options it was created
    with. None when its fingerprint cannot be taken yet (a plugin's that needs `use_dataset` first)."""
    try:
        made = own_fingerprint(method)
    except VPRBenchError:
        made = None  # said when the store asks for it
    set_attributes(method, name, source, **{MADE_FINGERPRINT: made})


def use_dataset(method, name: str) -> None:
    """`method.use_dataset(name)`, what a plugin's raises as its one line; the attributes it may set
    (AnyLoc's needs_fit) checked again after it, and the fingerprint it may change (AnyLoc's vocabulary)
    kept again for a method create_method made."""
    with plugin_part(method, "use_dataset"):
        method.use_dataset(name)
    check_attributes(method)
    restamp_fingerprint(method)


def restamp_fingerprint(method) -> None:
    """For a method create_method made, keep again the fingerprint vprbench's own calls left it with
    (use_dataset, a run's prepare naming the weights it loaded): only a change by hand is refused."""
    if hasattr(method, MADE_FINGERPRINT):
        stamp_fingerprint(method, method.name, source_of(type(method)))


def set_attributes(method, name: str, source: str, /, **values) -> None:
    """`method.<attribute> = value` for what vprbench sets (its name, options, batch size): a plugin's
    read-only property of that name is one line, not an AttributeError from vprbench's code."""
    for attribute, value in values.items():
        try:
            setattr(method, attribute, value)
        except (Exception, SystemExit) as error:
            if source_of(type(method)) == "vprbench":  # a bug of vprbench's keeps its traceback
                raise
            raise VPRBenchError(
                f"Method {name!r} ({source}) does not let vprbench set its {attribute} ({type(error).__name__}: "
                f"{error}): vprbench sets name, options, settings and batch_size itself; drop the plugin's own "
                f"{attribute} (or give it a setter) and fix the plugin.") from error
