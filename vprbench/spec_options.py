"""The method options a run's spec holds: those given on top of the preset, each in its one form
(`given_options`), the preset's defaults under them (`spec_options`), as plain data (`plain`)."""
from __future__ import annotations

import json
from typing import Any

from .errors import VPRBenchError, require
from .hashing import canonical_json
from .run_settings import RUN_SETTINGS


def plain(value: Any) -> Any:
    """`value` as plain data: tuples become lists (so a spec read back equals the one written)."""
    return json.loads(canonical_json(value))


def given_options(options, method: str | None = None, dataset: str | None = None) -> dict:
    """The options given that are part of a spec, each in its one form (methods/checks.py
    `canonical`): None (unset), run settings and (with the method's name) those set to the
    value they have anyway left out (an option naming the `dataset` evaluated among them)."""
    require(options or {}, dict, "options takes a dict of option name -> value, e.g. {'resize': [64, 64]}")
    names = [k for k in options or {} if not isinstance(k, str)]
    if names:
        raise VPRBenchError(f"Option names are text, e.g. {{'resize': [64, 64]}}; got {names[0]!r}.")
    from .methods.checks import canonical

    given = {k: canonical(k, v) for k, v in (options or {}).items() if v is not None and k not in RUN_SETTINGS}
    if method is not None:
        from .methods.registry import method_entry

        given = method_entry(method).without_defaults(given, dataset)
    return given


def spec_options(method: str, given: dict) -> dict:
    """A spec's options: `method`'s preset defaults (but run settings) under the options `given` (as
    `given_options` leaves them), which its stores are keyed by."""
    from .methods.registry import method_entry

    return plain({**{k: v for k, v in method_entry(method).defaults.items() if k not in RUN_SETTINGS}, **given})
