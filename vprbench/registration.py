"""What the method and stage registries share: the registry itself (`Registry`), the name rule,
who registered an entry, loading an entry's import path, and the one rule for names and plugins: a taken name is never replaced
(its results would be recorded under another's name), and an installed plugin that fails to
load is a warning, skipped, never the end of the command."""
from __future__ import annotations

import contextlib
import importlib
import unicodedata
import warnings

from .errors import VPRBenchError


def check_name(kind: str, name) -> None:
    """`name` is lower-case text without spaces; `kind` is "Method" or "Stage"."""
    if not isinstance(name, str) or not name or name != name.strip().lower() or " " in name:
        raise ValueError(f"{kind} names are lower-case without spaces, got {name!r}")
    # a line break or tab in a name splits the leaderboard's row in two (a forged row); '-x' reads as an option
    if any(c.isspace() or unicodedata.category(c)[0] == "C" for c in name) or name.startswith("-"):
        raise ValueError(f"{kind} names hold no whitespace or control characters and do not start with '-' (the "
                         f"command line reads that as an option); got {name!r}")
    if not unicodedata.is_normalized("NFC", name):  # 'é' as e + accent would be a second name that looks the same
        raise ValueError(f"{kind} names are written in Unicode NFC (composed), got {name!r} ({name.encode()!r}); "
                         "register it as unicodedata.normalize('NFC', name)")


def check_target(kind: str, name: str, target, description, source) -> None:
    """What an entry is registered with: a class or function (or its import path "module:attribute"),
    text for its description and source; else a ValueError now, not an unusable entry holding the name."""
    import re

    if not (callable(target) or isinstance(target, str) and re.fullmatch(r"[\w.]+:[\w.]+", target)):
        raise ValueError(f"{kind} {name!r}: register it with a class or function, or its import path "
                         f"'module:attribute'; got {type(target).__name__} {target!r}")
    for what, value in (("description", description), ("source", source)):
        if value is not None and not isinstance(value, str):
            raise ValueError(f"{kind} {name!r}: its {what} is text; got {type(value).__name__} {value!r}")


def looked_up(name):
    """A name as the registries hold it (NFC): one typed decomposed (e + accent) finds its entry."""
    return unicodedata.normalize("NFC", name) if isinstance(name, str) else name


def source_of(target) -> str:
    """Who registers `target` (an object, or its import path "module:attribute"): its top package."""
    module = target.partition(":")[0] if isinstance(target, str) else getattr(target, "__module__", "") or ""
    return module.split(".")[0] or "unknown"


#: what each plugin being loaded has claimed so far, innermost last, in every registry (a method
#: plugin may register stages too): taken out again if it fails; None while the core registers its own
_claims: list[list[tuple[dict, str]] | None] = []


def claim(registry: dict, kind: str, entry) -> None:
    """`entry` put under its name in `registry`, unless a different entry holds that name."""
    taken = registry.get(entry.name)
    if taken is not None and taken != entry and taken.source == entry.source:  # its own name, registered again
        why = ("with the same definition but other defaults or description" if taken.target == entry.target else
               "with another definition: a class defined again, as a notebook cell run again after an edit makes")
        raise ValueError(f"{kind} name {entry.name!r} is taken (registered by {taken.source} already, {why}); a name "
                         "is registered once per process, so register it under another name, or restart Python to "
                         "register it under this one")
    if taken is not None and taken != entry:
        raise ValueError(f"{kind} name {entry.name!r} is taken (registered by {taken.source}); register yours under "
                         "another name")
    if taken is None and _claims and _claims[-1] is not None:
        _claims[-1].append((registry, entry.name))
    registry[entry.name] = entry


@contextlib.contextmanager
def core_entries():
    """Within it the core registers its own entries: never a plugin's to take back (a registry's first
    use, which registers them, may come while a plugin of another registry loads)."""
    _claims.append(None)
    try:
        yield
    finally:
        _claims.pop()


def run_plugins(kind: str, found, registry: dict) -> list[str]:
    """Call the register function of every entry point in `found`; one that fails is skipped (what it
    claimed before failing, in `registry` or another, is taken out again), and named in what is returned
    ("'name' (module:function): error"), for an unknown name's message."""
    failed = []
    for ep in found:
        _claims.append([])
        try:
            ep.load()()
        except (Exception, SystemExit) as error:  # a broken plugin (sys.exit too) must not take the suite down
            for held, name in _claims[-1]:
                held.pop(name, None)
            reason = str(error) or type(error).__name__
            failed.append(f"{ep.name!r} ({ep.value}): {reason}")
            warnings.warn(f"{kind} plugin {ep.name!r} ({ep.value}) failed to load: {reason}", stacklevel=3)
        finally:
            _claims.pop()
    return failed


#: what to do about a plugin that cannot be imported
LOAD_FIX = "install what it needs or fix it (or uninstall the plugin)"


def unloaded_hint(kind: str, failed: list[str]) -> str:
    """For an unknown name: the plugins that failed to load may be what registers it."""
    if not failed:
        return ""
    which, whose = ("a plugin", "its") if len(failed) == 1 else ("one of the plugins", "their")
    return (f" It may come from {which} that failed to load: {'; '.join(failed)}. To use {whose} "
            f"{kind.lower()}s, {LOAD_FIX}.")


class Registry:
    """One kind's names -> entries (methods or stages): at its first use the core's, then the installed
    plugins' (entry points of `group`); after them whatever this process registers."""

    def __init__(self, kind: str, group: str, register_core):
        self.kind, self.group, self.register_core = kind, group, register_core
        self.entries: dict = {}
        self.loaded = False
        self.failures: list[str] = []  # plugins that failed to load, named when a name is unknown

    def installed(self) -> list:
        """The installed plugins' entry points."""
        from importlib.metadata import entry_points

        return list(entry_points(group=self.group))

    def load(self) -> None:
        if self.loaded:
            return
        self.loaded = True
        with core_entries():
            self.register_core()
        self.failures = run_plugins(self.kind, self.installed(), self.entries)

    def claim(self, entry) -> None:
        """`entry` under its name: the core's and installed plugins' names are taken before any other."""
        self.load()
        claim(self.entries, self.kind, entry)

    def available(self) -> dict:
        self.load()
        return dict(sorted(self.entries.items()))

    def unloaded_hint(self) -> str:
        """For a name that is unknown: the plugins that failed to load, which may register it ('' if none)."""
        self.load()
        return unloaded_hint(self.kind, self.failures)


def imported(kind: str, name: str, source: str, target):
    """`target` itself, or the object its import path "module:attribute" names."""
    if not isinstance(target, str):
        return target
    module, _, attribute = target.partition(":")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (Exception, SystemExit) as error:  # a module that raises or exits when imported, as a plugin may
        raise VPRBenchError(f"{kind} {name!r} ({source}) cannot be loaded from {target}: "
                            f"{str(error) or type(error).__name__}; {LOAD_FIX}.") from None
