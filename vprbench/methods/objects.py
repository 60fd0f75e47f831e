"""A method object handed to the Python API (`spec_for`, `evaluate(..., method=...)`): is it the
method its name and options say? The record labels its results with them."""
from __future__ import annotations

import inspect

from ..errors import VPRBenchError, require
from ..spec_options import given_options, plain
from ..text import shortened
from .attributes import MADE_FINGERPRINT, check_attributes, own_fingerprint
from .base import Method
from .registry import method_entry


def created_as(method) -> str:
    """The name a method object was created under (`vprbench.create_method`), checked: an object
    renamed after creation (a HOG whose `name` was set to 'sad', a VLAD preset renamed to a GeM
    one of the same class) would be recorded as another method. Its name and options must be
    those `create_method` stamped it with, and its class the one its name is registered with."""
    require(method, Method, "method takes a vprbench.Method object made by vprbench.create_method(name, ...)")
    if not isinstance(method.name, str) or not method.name:
        raise VPRBenchError(f"The method object {type(method).__name__} has no name: register its factory "
                            "(vprbench.register_method(name, factory)) and create it with vprbench.create_method(name).")
    stamp = getattr(method, "_created_as", None)
    if stamp is not None and (method.name, getattr(method, "options", None)) != stamp:
        raise VPRBenchError(f"The method object was created as {stamp[0]!r} with options {stamp[1]}, but now says "
                            f"{method.name!r} with options {getattr(method, 'options', None)}: a method cannot be "
                            f"renamed or given other options; create it with vprbench.create_method(name, ...).")
    factory = method_entry(method.name).factory
    if inspect.isclass(factory) and not isinstance(method, factory):
        raise VPRBenchError(f"The method object is a {type(method).__name__}, but its name says {method.name!r}, which "
                            f"is a {factory.__name__}: a method cannot be renamed; create it with "
                            f"vprbench.create_method({method.name!r}, ...).")
    check_attributes(method)  # an object built without create_method is checked as one built with it
    check_unchanged(method)
    return method.name


def check_unchanged(method) -> None:
    """The method computes what it was created to (its fingerprint as create_method kept it, or as its
    dataset last set it): an attribute set by hand (`m.size = 4`) would be evaluated, stored and recorded
    under the name and options it was created with, and serve a later run of those options."""
    made = getattr(method, MADE_FINGERPRINT, None)
    if made is None:  # not made by create_method, or its fingerprint not known yet
        return
    now = own_fingerprint(method)
    changed = sorted(k for k in set(made) | set(now) if made.get(k) != now.get(k))
    if not changed:
        return
    said = "; ".join(f"{k}: {_value(made, k)} then, {_value(now, k)} now" for k in changed)
    options = dict(getattr(method, "options", {}) or {})
    if set(changed) <= set(method_entry(method.name).options()):  # e.g. create_method('thumb', size=4)
        written = ", ".join([repr(method.name)] + [f"{k}={v!r}" for k, v in {**options, **{k: now[k] for k in changed
                                                                                             if k in now}}.items()])
        todo = f"create it again with the option, e.g. vprbench.create_method({written})"
    else:
        todo = f"create it again with vprbench.create_method({method.name!r}, ...) and leave its attributes as made"
    raise VPRBenchError(f"The method object {method.name!r} (options {options}) was changed after create_method: its "
                        f"fingerprint differs ({said}), so its results would be recorded and "
                        f"stored as those options'; {todo}.")


def _value(fingerprint: dict, key: str) -> str:
    return shortened(repr(fingerprint[key])) if key in fingerprint else "unset"


def check_method(method, spec) -> None:
    """A method given already built to `evaluate` must be the one `spec` names: its name and the
    options it was created with (else the record would label its results with the spec's)."""
    name = created_as(method)
    try:
        given = plain(given_options(dict(getattr(method, "options", {}) or {}), name, spec.dataset.name))
    except (TypeError, ValueError):
        given = None
    if name != spec.method or given != spec.given:
        raise VPRBenchError(f"The method given is {name!r} with options {getattr(method, 'options', {})}, but the spec "
                            f"is {spec.method!r} with options {spec.given}: make the spec with "
                            "vprbench.spec.spec_for(method, dataset).")
