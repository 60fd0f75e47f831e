"""Name -> method factory. Core methods and the baselines register by name (their code is
imported only when a method is built); other packages through entry points.

A separate package adds methods without touching vprbench by declaring, in its
pyproject.toml::

    [project.entry-points."vprbench.methods"]
    my-methods = "my_package:register"

where `my_package.register()` calls `vprbench.register_method(...)` with a factory, or with
the factory's import path ("my_package.model:MyMethod") so listing methods stays instant.
"""
from __future__ import annotations

import copy
import inspect
import json
import math
import re
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import MethodNeed, VPRBenchError, closest_names
from ..loader import plugin_part
from ..paths import folder_path
from ..registration import Registry, check_name, check_target, imported, looked_up, source_of
from ..text import shortened
from .attributes import MAX_BATCH_SIZE, check_attributes, set_attributes, stamp_fingerprint
from .checks import canonical, plain_options, whole

ENTRY_POINT_GROUP = "vprbench.methods"
#: what the registry hands a factory that takes it, never an option a user sets
LOCATIONS = ("cache_dir", "data_dir")


@dataclass(frozen=True)
class MethodEntry:
    name: str
    target: Callable | str  # the factory, or its import path "module:attribute"
    defaults: dict = field(default_factory=dict)
    description: str = ""
    source: str = "vprbench"

    @property
    def factory(self) -> Callable:
        found = imported("Method", self.name, self.source, self.target)
        if not callable(found):
            raise VPRBenchError(f"Method {self.name!r} ({self.source}) is registered with {self.target!r}, which is "
                                "not a class or function returning a vprbench.Method; fix the plugin.")
        return found

    @property
    def compare(self) -> str | None:
        """How its methods compare descriptors when the factory says so unmade (a class attribute, e.g.
        sad's); None when only the method made knows (a function factory, a property)."""
        found = getattr(self.factory, "compare", None)
        return found if isinstance(found, str) else None

    def factory_options(self, *, required: bool = False) -> list[str]:
        """Keyword options the factory itself accepts (`required`: those it has no default for)."""
        params = inspect.signature(self.factory).parameters.values()
        return [p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
                and not (required and p.default is not p.empty)]

    def options(self) -> list[str]:
        """Options the method takes: the factory's (but the locations), and batch_size, which every method takes."""
        own = [o for o in self.factory_options() if o not in LOCATIONS]
        return own + ([] if "batch_size" in own else ["batch_size"])

    def effective_defaults(self) -> dict:
        """What an option is when not given: the preset's value, else the factory's own default."""
        params = inspect.signature(self.factory).parameters.values()
        own = {p.name: p.default for p in params if p.default is not p.empty and p.name not in LOCATIONS}
        return {**own, **self.defaults}

    def in_factory(self, part: str):
        """Runs a call into the factory's code (a hook, or the factory itself): a plugin's failure is one line."""
        return plugin_part(self.factory, part, f"Method {self.name!r}")

    def cached_identities(self, options: dict, dataset: str, cache_dir=None) -> dict[str, str]:
        """`Method.cached_identities` of the factory (a plugin's function factory has none)."""
        found = getattr(self.factory, "cached_identities", None)
        if not callable(found):
            return {}
        # a copy: the spec's options key the run
        return self.hook("cached_identities", lambda: found(copy.deepcopy(options), dataset, cache_dir), str)

    def hook(self, part: str, call, values=object) -> dict:
        """What the factory's hook `part` returns (by `call()`): a dict of option name -> `values`, else one
        line naming the plugin (not an AttributeError from vprbench's line, nor a spec refusing it later)."""
        with self.in_factory(part):
            found = call()
        if not isinstance(found, dict) or not all(isinstance(k, str) and isinstance(v, values)
                                                  for k, v in found.items()):
            what = "text" if values is str else "value"
            raise VPRBenchError(f"Method {self.name!r} ({self.source}): its {part}() returned {shortened(repr(found))}; "
                                f"it returns a dict of option name -> {what}. Fix the plugin.")
        return found

    def in_form(self, given: dict) -> dict:
        """`given` with a list written as text ('4,6,8,10' from `-o bin_sizes=4,6,8,10`) as that list,
        for an option whose default is a list, and a number written as text ('4' in a plan or from
        Python) as that number, for an option that takes a number (the method reads both alike)."""
        defaults, numeric = self.effective_defaults(), self.numeric_options()
        return {k: _listed(v) if isinstance(defaults.get(k), (list, tuple)) else
                _numbered(v) if k in numeric else v for k, v in given.items()}

    def numeric_options(self) -> set[str]:
        """Options that take a number only: annotated int/float (optionally None), else defaulting to one."""
        try:
            params = inspect.signature(self.factory, eval_str=True).parameters.values()
        except (NameError, TypeError, SyntaxError, AttributeError):  # a plugin's annotation not resolvable here
            params = inspect.signature(self.factory).parameters.values()
        found = {p.name for p in params if _number_annotation(p.annotation)}
        found |= {k for k, v in self.effective_defaults().items()
                  if isinstance(v, (int, float)) and not isinstance(v, bool)}
        return found

    def without_defaults(self, given: dict, dataset: str | None = None) -> dict:
        """`given` less the options set to the value they have anyway (`cell = 16` for hog): one
        computation, one identity (spec, store, label), whether a default is written out or not. A list
        written as text ('4,6,8,10' from `-o bin_sizes=4,6,8,10`) for an option whose default is a list
        is that list. With the `dataset` evaluated, the factory's `dataset_option` naming it is as unset."""
        defaults = self.effective_defaults()
        given = self.in_form(given)
        implied = getattr(self.factory, "implied_options", None)  # an unset option's value, from the others
        # copies: a hook appending to a list option would change the preset (and the options given)
        implied = self.hook("implied_options", lambda: implied(copy.deepcopy({**defaults, **given}))) \
            if callable(implied) else {}
        defaults |= {k: v for k, v in implied.items() if defaults.get(k) is None}
        named = getattr(self.factory, "dataset_option", None)  # unset, it is the dataset evaluated (use_dataset)
        if dataset is not None and isinstance(named, str) and defaults.get(named) is None:
            defaults[named] = dataset
        # a file the factory's default names stays given: unlike a preset's, that default is not in the
        # spec's options, so its content (spec.files) would leave the run's identity
        kept = {k: v for k, v in given.items() if k not in defaults or not _same(k, v, defaults[k])
                or k not in self.defaults and _names_a_path(v)}
        unused = getattr(self.factory, "unused_options", None)  # options the other options leave idle
        unused = self.hook("unused_options", lambda: unused(copy.deepcopy({**defaults, **given}))) \
            if callable(unused) else {}
        idle = {k: why for k, why in unused.items() if k in kept}
        if idle:
            name, why = sorted(idle.items())[0]
            raise VPRBenchError(f"Method {self.name!r}: option {name}={kept[name]!r} is not used here ({why}): drop it "
                                "(a row would name it, computed without it).")
        return kept


def _register_core() -> None:
    from .builtin import core_methods

    for entry in core_methods():
        register_method(**entry)


METHODS = Registry("Method", ENTRY_POINT_GROUP, _register_core)


def register_method(
    name: str,
    factory: Callable[..., "Method"] | str,  # noqa: F821
    *,
    defaults: dict | None = None,
    description: str = "",
    source: str | None = None,
) -> None:
    """Make `name` available to `vprbench evaluate --method name`.

    `factory(**options)` returns a `Method` (or give its import path, "module:attribute");
    `defaults` are the preset's options, which the user's options override. Registering the same
    factory again with the same defaults and description changes nothing. A name already taken
    (by another factory: a class defined again, as a notebook cell run again makes, is another; or
    by this one with other defaults or description), a factory neither callable nor an import path,
    defaults that are no dict, a description that is no text: a ValueError, and nothing is registered.
    """
    check_name("Method", name)
    check_target("Method", name, factory, description, source)
    if defaults is not None and not isinstance(defaults, dict):
        raise ValueError(f"Method {name!r}: defaults takes a dict of option name -> value; got {defaults!r}")
    if defaults:  # checked now, as a user's options are: else each command using the method is a traceback
        bad = [k for k in defaults if not isinstance(k, str)]
        try:
            if bad:
                raise VPRBenchError(f"Method {name!r}: an option's name is text, not {bad[0]!r}.")
            plain_options(name, defaults)
        except VPRBenchError as error:
            raise ValueError(f"{str(error).rstrip('.')}, in its defaults: register plain data (numbers, text, "
                             "lists, tables; no NaN).") from None
    entry = MethodEntry(name, factory, dict(defaults or {}), description, source or source_of(factory))
    METHODS.claim(entry)


def available_methods() -> dict[str, MethodEntry]:
    return METHODS.available()


def failed_plugins_hint() -> str:
    """For a method name that is unknown: the plugins that failed to load, which may register it ('' if none)."""
    return METHODS.unloaded_hint()


def method_entry(name: str) -> MethodEntry:
    methods, name = available_methods(), looked_up(name)
    if not isinstance(name, str) or name not in methods:  # a list would be unhashable here
        raise VPRBenchError(
            f"Unknown method {name!r}.{closest_names(name, methods)} "
            f"Run 'vprbench methods list' to see all methods.{failed_plugins_hint()}"
        )
    return methods[name]


def create_method(name: str, *, cache_dir=None, data_dir=None, **options) -> "Method":  # noqa: F821
    """Build the method `name` with its preset defaults overridden by `options` (None = unset).

    Every option is checked here or by the method's constructor, before anything is loaded.
    The registry handles `batch_size` for every method (a whole number >= 1; passed to the
    factory when it takes it, else set on the method), checks `device` for those taking it and
    hands `cache_dir` and `data_dir` to factories that take them. The method gets `name`, `options` (what the
    user gave) and `settings` (preset + user options, what the store is keyed on), and keeps its
    `fingerprint()` as made: changed afterwards (`m.size = 4`), `spec_for` and `evaluate(method=m)`
    refuse it (its results would be stored and recorded under the options it was created with).
    """
    from .base import Method

    if isinstance(name, Method):  # else 'Unknown method <... object at 0x...>'
        raise VPRBenchError(f"create_method takes a method's name, e.g. 'hog'; got the method object "
                            f"{getattr(name, 'name', '') or type(name).__name__!r}, already created: use it as it is.")
    entry = method_entry(name)
    cache_dir, data_dir = folder_path(cache_dir, "cache_dir"), folder_path(data_dir, "data_dir")
    # each value in its one form (resize '64x64' is [64, 64]), as a spec holds it: one store either way
    written = entry.in_form({k: canonical(k, v) for k, v in options.items() if v is not None})
    plain_options(name, written)  # before the factory sees it, as a spec does
    given = entry.without_defaults(written)
    merged = {**entry.defaults, **given}
    accepted = entry.options()
    unknown = sorted(set(merged) - set(accepted) - ({"device"} if "device" not in accepted else set()))
    if unknown:
        raise VPRBenchError(
            f"Method {name!r} does not take option(s) {', '.join(unknown)}.{closest_names(unknown[0], accepted)} "
            f"It accepts: {', '.join(accepted) or 'none'}."
        )
    if "device" not in accepted:  # a method without a device runs where it runs
        merged.pop("device", None)
        given.pop("device", None)
    merged = checked_run_options(name, merged)  # before a plugin loads its weights
    takes = entry.factory_options()
    # an option written out at the value it has anyway still reaches the factory: AnyLoc's layer=9 on
    # ViT-S is the user's choice, not the preset's layer moved to the same depth (which it notes)
    chosen = {k: v for k, v in written.items() if k not in given and k not in ("batch_size", "device")}
    arguments = {k: v for k, v in {**merged, **chosen}.items() if k in takes}
    for location, folder in (("cache_dir", cache_dir), ("data_dir", data_dir)):
        if location in takes and folder is not None:
            arguments[location] = folder
    factory = entry.factory
    missing = sorted(getattr(factory, "__abstractmethods__", ())) if isinstance(factory, type) else []
    if missing:  # else a TypeError raised inside vprbench, whose line it would name as the plugin's
        raise VPRBenchError(f"Method {name!r} ({entry.source}): {factory.__name__} does not define "
                            f"{', '.join(m + '()' for m in missing)}, which every vprbench.Method needs; define it "
                            "(see 'Add your method', the contract).")
    needed = [o for o in entry.factory_options(required=True) if o not in arguments and o not in LOCATIONS]
    if needed:  # else a TypeError at the call here, whose line would be named as the plugin's
        raise VPRBenchError(f"Method {name!r} ({entry.source}) needs option(s) {', '.join(needed)}, for which it has no "
                            f"default: give {'them' if len(needed) > 1 else 'it'}, e.g. -o {needed[0]}=VALUE.")
    try:
        with entry.in_factory(f"its factory {getattr(factory, '__name__', type(factory).__name__)}"):
            method = factory(**copy.deepcopy(arguments))  # a factory appending to a list would change the preset
    except MethodNeed as need:  # its command names the preset as created and this run's folders, to paste
        raise VPRBenchError(need.said(entry.name, {"data-dir": data_dir, "cache-dir": cache_dir})) from None
    if not isinstance(method, Method):
        raise VPRBenchError(f"Method {name!r} ({entry.source}): its factory returned {type(method).__name__}, not a "
                            "vprbench.Method; return an instance of a subclass of vprbench.Method (see 'Add your "
                            "method', the contract).")
    if "batch_size" in merged:
        set_attributes(method, name, entry.source, batch_size=merged["batch_size"])
    check_attributes(method, name, entry.source)  # compare, batch_size, ...: before any image is described
    options = {k: v for k, v in given.items() if k not in ("device", "batch_size")}
    set_attributes(method, name, entry.source, name=entry.name, options=options,
                   settings={k: v for k, v in merged.items() if k not in ("device", "batch_size")},
                   _created_as=(entry.name, copy.deepcopy(options)))  # what `name`/`options` may not be changed from
    stamp_fingerprint(method, name, entry.source)  # nor what it computes (`m.size = 4`): objects.py refuses it
    return method


def _same(name: str, value, default) -> bool:
    if default is None:  # "unset": decided by the method (netvlad-vgg16's resize), never a value one writes
        return False
    try:
        return json.dumps(canonical(name, value), sort_keys=True) == json.dumps(canonical(name, default), sort_keys=True)
    except (TypeError, ValueError):  # not plain data: never taken for a default
        return False


def _number_annotation(annotation) -> bool:
    """int, float, int | None, float | None (not bool, nor a union with text or a size)."""
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    kinds = set(typing.get_args(annotation)) if union else {annotation}
    return kinds - {type(None)} <= {int, float} and kinds != {type(None)}


def _numbered(value):
    """'4' -> 4, '3.5' -> 3.5, '3.0' -> 3; anything else as it is (the method names what it refuses)."""
    if not isinstance(value, str):
        return value
    try:
        number = float(value)
    except ValueError:
        return value
    return canonical("", number) if math.isfinite(number) else value


def _listed(value):
    """'4,6,8' (or '4') -> [4, 6, 8]; anything else as it is (the method names what it refuses)."""
    if not isinstance(value, str) or not re.fullmatch(r"\s*-?\d+(\s*,\s*-?\d+)*\s*", value):
        return value
    return [int(item) for item in value.split(",")]


def _names_a_path(value) -> bool:
    try:
        return isinstance(value, str) and bool(value) and Path(value).expanduser().exists()
    except RuntimeError:  # '~name' of no user here: the method names it
        return False


def checked_run_options(name: str, options: dict) -> dict:
    """`options` with the run settings every method takes, batch_size and device, checked (a plan
    checks its entries with this before any cell runs)."""
    from .checks import device

    options = dict(options)
    if "batch_size" in options:
        options["batch_size"] = whole(name, "batch_size", options["batch_size"], 1, what="images per batch")
        if options["batch_size"] > MAX_BATCH_SIZE:
            raise VPRBenchError(f"{name}: option batch_size takes at most {MAX_BATCH_SIZE} images per batch; "
                                f"got {options['batch_size']}.")
    if options.get("device") is not None:
        options["device"] = device(name, options["device"])
    return options
