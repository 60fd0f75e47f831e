"""Name -> method factory. Core methods register on import; others through entry points.

A separate package adds methods without touching vprbench by declaring, in its
pyproject.toml::

    [project.entry-points."vprbench.methods"]
    my-methods = "my_package:register"

where `my_package.register()` calls `vprbench.register_method(...)`.
"""
from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib.metadata import entry_points

from ..errors import VPRBenchError, closest_names
from .base import Method
from .checks import device, whole

ENTRY_POINT_GROUP = "vprbench.methods"


@dataclass(frozen=True)
class MethodEntry:
    name: str
    factory: Callable[..., Method]
    defaults: dict = field(default_factory=dict)
    description: str = ""
    source: str = "vprbench"

    def factory_options(self) -> list[str]:
        """Keyword options the factory itself accepts."""
        params = inspect.signature(self.factory).parameters.values()
        return [p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)]

    def options(self) -> list[str]:
        """Options the method takes: the factory's, and batch_size, which every method takes."""
        own = self.factory_options()
        return own + ([] if "batch_size" in own else ["batch_size"])


_REGISTRY: dict[str, MethodEntry] = {}
_plugins_loaded = False


def register_method(
    name: str,
    factory: Callable[..., Method],
    *,
    defaults: dict | None = None,
    description: str = "",
    source: str | None = None,
) -> None:
    """Make `name` available to `vprbench evaluate --method name`.

    `factory(**options)` returns a `Method`; `defaults` are the preset's options,
    which the user's options override.
    """
    if not name or name != name.strip().lower() or " " in name:
        raise ValueError(f"Method names are lower-case without spaces, got {name!r}")
    if source is None:
        module = getattr(factory, "__module__", "") or ""
        source = module.split(".")[0] or "unknown"
    _REGISTRY[name] = MethodEntry(name, factory, dict(defaults or {}), description, source)


def _load_plugins() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    from . import builtin  # noqa: F401  core methods register themselves

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            register = ep.load()
            register()
        except Exception as error:  # a broken plugin must not take the suite down
            import warnings

            warnings.warn(f"Method plugin {ep.name!r} ({ep.value}) failed to load: {error}", stacklevel=2)


def available_methods() -> dict[str, MethodEntry]:
    _load_plugins()
    return dict(sorted(_REGISTRY.items()))


def method_entry(name: str) -> MethodEntry:
    methods = available_methods()
    if name not in methods:
        raise VPRBenchError(
            f"Unknown method {name!r}.{closest_names(name, methods)} "
            "Run 'vprbench methods list' to see all methods."
        )
    return methods[name]


def create_method(name: str, **options) -> Method:
    """Build the method `name` with its preset defaults overridden by `options` (None = unset).

    Every option is checked here or by the method's constructor, before anything is loaded.
    The registry handles `batch_size` for every method (a whole number >= 1; passed to the
    factory when it takes it, else set on the method) and checks `device` for those taking it. The method gets `name`, `options`
    (what the user gave) and `settings` (preset + user options, what the store is keyed on).
    """
    entry = method_entry(name)
    given = {k: v for k, v in options.items() if v is not None}
    merged = {**entry.defaults, **given}
    accepted = entry.options()
    unknown = sorted(set(merged) - set(accepted))
    if unknown:
        raise VPRBenchError(
            f"Method {name!r} does not take option(s) {', '.join(unknown)}; "
            f"it accepts: {', '.join(accepted) or 'none'}."
        )
    if "batch_size" in merged:
        merged["batch_size"] = whole(name, "batch_size", merged["batch_size"], 1, what="images per batch")
    if merged.get("device") is not None and "device" in accepted:  # before a plugin loads its weights
        merged["device"] = device(name, merged["device"])
    takes_batch_size = "batch_size" in entry.factory_options()
    method = entry.factory(**{k: v for k, v in merged.items() if takes_batch_size or k != "batch_size"})
    if not isinstance(method, Method):
        raise VPRBenchError(f"Method {name!r} ({entry.source}) did not return a vprbench.Method")
    if "batch_size" in merged:
        method.batch_size = merged["batch_size"]
    if isinstance(method.batch_size, bool) or not isinstance(method.batch_size, int) or method.batch_size < 1:
        raise VPRBenchError(f"Method {name!r} ({entry.source}) has batch_size {method.batch_size!r}; "
                            "it must be a whole number >= 1 (fix the plugin, or pass --batch-size).")
    method.name = name
    method.options = given
    method.settings = merged
    return method
