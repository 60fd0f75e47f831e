"""Plans: methods (with options) x datasets (with protocols) x K values, as cells, each a run spec.

A plan file (TOML):

    name = "corridor-check"          # optional
    k = [1, 5, 10]                   # optional (default 1 5 10 20)
    search = { index = "hnsw" }      # optional (default exact)
    store_dtype = "float16"          # optional (default float32)
    stages = [{ name = "sift-ransac", k = 100 }]   # optional: post-retrieval stages of every cell

    [[methods]]
    name = "hog"
    options = { resize = [64, 64] }

    [[methods]]
    name = "dense-vlad"
    stages = [{ name = "aqe", k = 20 }]   # optional: this entry's stages (over the plan's)

    [[datasets]]
    name = "corridor"
    protocols = ["vpr-bench"]        # optional (default: the dataset's first protocol)

`methods = ["hog", "dense-vlad"]` and `datasets = ["corridor"]` are accepted too. Every
problem (unknown key, method, option, dataset or protocol) is listed at once, with its line,
before anything runs. Each cell is resolved by `vprbench.spec.resolve_spec`, as a single
evaluation is; options given on the command line override the plan's.
"""
from __future__ import annotations

import re
import reprlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import ProblemList, VPRBenchError, closest_names, toml_data
from ..paths import regular_file
from ..registration import looked_up
from ..spec import (RUN_SETTINGS, STORE_DTYPES, RunSettings, RunSpec, _choice, check_ks, resolve_dataset, resolve_search,
                    resolve_spec, resolve_stage, split_run_settings)
from ..text import one_line

PLAN_KEYS = {"name", "description", "k", "methods", "datasets", "search", "store_dtype", "stages"}
METHOD_KEYS = {"name", "options", "label", "stages"}
DATASET_KEYS = {"name", "protocols", "protocol"}


@dataclass(frozen=True, eq=False)
class Cell:
    """One run of a sweep: its spec, the run settings its plan entry sets (e.g. batch_size),
    and the row label a paper's table gives it."""

    spec: RunSpec
    settings: dict = field(default_factory=dict)
    label: str = ""

    @property
    def key(self) -> str:
        return self.spec.key

    def title(self) -> str:
        return f"{self.label} | {self.spec.dataset.protocol_id}" if self.label else self.spec.title()


@dataclass
class Plan:
    name: str
    cells: list[Cell]
    description: str = ""


def _line_index(text: str) -> dict[tuple[str, int, str], int]:
    """(section, entry number, key) -> 1-based line, for `key = ...` lines; section "" is the top."""
    found, section, counts = {}, "", {}
    for number, line in enumerate(text.splitlines(), 1):
        header = re.match(r"^\s*\[\[\s*([A-Za-z0-9_.-]+)\s*\]\]", line) or re.match(r"^\s*\[\s*([A-Za-z0-9_.-]+)\s*\]", line)
        if header:
            section = header.group(1)
            counts[section] = counts.get(section, -1) + 1
            found.setdefault((section, counts[section], ""), number)
            continue
        key = re.match(r"^\s*([A-Za-z0-9_-]+)\s*=", line)
        if key:
            found.setdefault((section, counts.get(section, 0), key.group(1)), number)
    return found


def read_plan(path: str | Path, *, overrides: dict | None = None, data_dir=None, cache_dir=None) -> Plan:
    return read_entries(path, overrides=overrides).plan(data_dir, cache_dir)


def read_entries(path: str | Path, *, overrides: dict | None = None) -> PlanEntries:
    """A plan file's entries, checked; no dataset read yet (see `PlanEntries`)."""
    path = Path(path)
    regular_file(path, "Plan")  # a named pipe would hang the read
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise VPRBenchError(f"Cannot read plan {path}: {error.strerror or error}.") from None
    except UnicodeDecodeError:
        raise VPRBenchError(f"Plan {path} is not a UTF-8 text file.") from None
    data = toml_data(text, f"Plan {path}")
    return plan_entries(data, str(path), _line_index(text), overrides=overrides, default_name=path.stem)


def build_plan(data: dict, origin: str, lines: dict | None = None, *, overrides: dict | None = None,
               data_dir=None, cache_dir=None, default_name: str = "plan") -> Plan:
    """Cells of a plan given as a dict; raises one error listing every problem.

    `overrides` are what the command line sets on top of every entry: `options` (method options,
    run settings among them), `search`, `store_dtype`, `k`, `stages` (replacing every entry's).
    """
    return plan_entries(data, origin, lines, overrides=overrides, default_name=default_name).plan(data_dir, cache_dir)


@dataclass
class PlanEntries:
    """A plan's entries, checked, before its cells are made: making them reads each folder of one's
    own (and remembers its images in the cache), so what the datasets are is known before that."""

    name: str
    description: str
    origin: str
    where: Callable[[str, int, str], str]  # (section, entry, key) -> "origin:line"
    methods: list  # (entry, name, options, label, stages)
    datasets: list  # (entry, name, protocol)
    shared: dict  # ks, search, store_dtype

    def plan(self, data_dir=None, cache_dir=None) -> Plan:
        """The cells, each spec resolved; raises one error listing every problem."""
        from ..datasets import is_path

        cells, problems, folders = [], [], {}
        for d, dataset, protocol in self.datasets:
            if is_path(dataset):  # read once for every method; a fault is its entry's, told once at its line
                try:
                    folders[d, protocol] = resolve_dataset(dataset, protocol, data_dir, cache_dir)
                except VPRBenchError as error:
                    problems.append(f"{self.where('datasets', d, 'name')}: {error}")
                    folders[d, protocol] = None
        for m, method, options, label, stages in self.methods:
            for d, dataset, protocol in self.datasets:
                dataset = folders.get((d, protocol), dataset)
                if dataset is None:
                    continue
                given, run_options = split_run_settings(options)
                try:
                    spec = resolve_spec(method, dataset, options=given, protocol=protocol, data_dir=data_dir,
                                        cache_dir=cache_dir, stages=stages, **self.shared)
                except VPRBenchError as error:
                    problems.append(f"{self.where('methods', m, 'options')}: {error}")
                    continue
                cells.append(Cell(spec, run_options, label))
        _raise_problems(self.origin, problems)
        return Plan(name=self.name, cells=cells, description=self.description)


def _raise_problems(origin: str, problems: list[str]) -> None:
    if problems:
        # a ProblemList prints its line breaks: the path's are written out, as in its problems
        what = "The command line" if origin == "the command line" else f"Plan {one_line(origin)}"
        shown = list(dict.fromkeys(one_line(p) for p in problems))  # a problem every cell has is one, counted once
        raise ProblemList(f"{what} has {len(shown)} problem(s); nothing was run:\n  " + "\n  ".join(shown))


def plan_entries(data: dict, origin: str, lines: dict | None = None, *, overrides: dict | None = None,
                 default_name: str = "plan") -> PlanEntries:
    """A plan given as a dict, checked (see `build_plan`); raises one error listing every problem."""
    from ..datasets import dataset_manifests, is_path
    from ..datasets.protocol import protocols
    from ..evaluation.retrieve import check_compare
    from ..methods import available_methods
    from ..methods.registry import checked_run_options, failed_plugins_hint
    from ..stages.registry import create_stage
    from ..stages.run import check_compares, check_stage_chain

    lines, overrides = lines or {}, dict(overrides or {})
    problems: list[str] = []

    def where(section: str, index: int, key: str) -> str:
        line = lines.get((section, index, key)) or lines.get((section, index, "")) or lines.get(("", 0, section))
        return f"{origin}:{line}" if line else origin

    for key in sorted(set(data) - PLAN_KEYS):
        problems.append(f"{where('', 0, key)}: unknown key {key!r}{closest_names(key, PLAN_KEYS)} (allowed: {', '.join(sorted(PLAN_KEYS))})")
    for key in ("name", "description"):  # else a table or list is shown as its Python spelling
        if not isinstance(data.get(key, ""), str):
            problems.append(f"{where('', 0, key)}: the plan's {key} must be a text; got {reprlib.repr(data[key])}")
    shared = {"ks": overrides.get("k") or data.get("k"), "search": layered_search(data.get("search"), overrides.get("search")),
              "store_dtype": overrides.get("store_dtype") or data.get("store_dtype", "float32")}
    for key, check in (("k", lambda: check_ks(shared["ks"])), ("search", lambda: resolve_search(shared["search"])),
                       ("store_dtype", lambda: _choice("--store-dtype", shared["store_dtype"], STORE_DTYPES))):
        try:  # with the other problems, at its own line (not each cell's, after them)
            check()
        except VPRBenchError as error:
            problems.append(f"{where('', 0, key)}: {error}")

    try:
        search = resolve_search(shared["search"])
    except VPRBenchError:
        search = None  # named above, at its own line
    try:
        ks = check_ks(shared["ks"])
    except VPRBenchError:
        ks = None  # named above, at its own line
    methods, known_methods = [], available_methods()
    for i, entry in enumerate(_entries(data, "methods", problems, where)):
        entry = {"name": entry} if isinstance(entry, str) else entry
        for key in sorted(set(entry) - METHOD_KEYS):
            problems.append(f"{where('methods', i, key)}: method entry {i + 1} has unknown key {key!r} (allowed: {', '.join(sorted(METHOD_KEYS))})")
        name = looked_up(entry.get("name"))  # typed decomposed (e + accent): its NFC entry, as on the command line
        if not isinstance(name, str) or name not in known_methods:
            problems.append(f"{where('methods', i, 'name')}: unknown method {reprlib.repr(name)}.{closest_names(str(name), known_methods)}"
                            f" Run 'vprbench methods list'.{failed_plugins_hint()}")
            continue
        options = entry.get("options", {})
        if not isinstance(options, dict):
            problems.append(f"{where('methods', i, 'options')}: options of method {name!r} must be a table, got {options!r}")
            continue
        options = {**options, **{k: v for k, v in (overrides.get("options") or {}).items() if v is not None}}
        accepted = known_methods[name].options()
        if "device" not in accepted:  # given to methods that take one
            options.pop("device", None)
        named = [o for o in accepted if o not in RUN_SETTINGS]  # as a single run names them: run settings apart
        for option in sorted(set(options) - set(accepted) - set(RUN_SETTINGS)):
            problems.append(f"{where('methods', i, 'options')}: method {name!r} does not take option {option!r}."
                            f"{closest_names(option, named)} (It accepts: {', '.join(named) or 'none'}.)")
        try:  # run settings' values too, so a bad batch_size stops the plan, not each of its cells
            RunSettings().with_options(checked_run_options(name, options))
        except VPRBenchError as error:
            problems.append(f"{where('methods', i, 'options')}: {error}")
        if "resize" in options and "resize" in accepted:  # one parser for every method's: checked here, not per cell
            from ..features.resize import parse_size

            try:
                parse_size(options["resize"])
            except VPRBenchError as error:
                problems.append(f"{where('methods', i, 'options')}: Method {name!r}: {error}")
        if search is not None:  # the single run's check, at the method's line: not when its cells run
            try:
                check_compare(name, known_methods[name].compare, search.index, search.options)
            except VPRBenchError as error:
                problems.append(f"{where('methods', i, 'name')}: {error}")
        stages = overrides.get("stages") or entry.get("stages", data.get("stages", []))
        if not isinstance(stages, list):
            problems.append(f"{where('methods', i, 'stages')}: stages of method {name!r} must be a list of tables, "
                            f"e.g. [{{ name = \"aqe\", k = 20 }}]; got {stages!r}")
            continue
        # the stages' own problems at the line they are written on: the plan's shared ones once, not at each entry
        stages_at = ("the command line" if overrides.get("stages") else
                     where('methods', i, 'stages') if "stages" in entry else where('', 0, 'stages'))
        try:
            chain = tuple(resolve_stage(stage) for stage in stages)
            if ks is not None:
                check_stage_chain(chain, ks)
        except VPRBenchError as error:
            problems.append(f"{stages_at}: {error}")
            continue
        compare = known_methods[name].compare  # None: only the method made knows (its cells check it)
        try:  # a stage that cannot use the method's comparison (aqe on sad), as the single run refuses it
            check_compares([create_stage(stage.name, stage.options) for stage in chain] if compare else [], compare)
        except VPRBenchError as error:
            problems.append(f"{where('methods', i, 'name')}: Method {name!r}: {error}")
            continue
        if not isinstance(entry.get("label", ""), str):
            problems.append(f"{where('methods', i, 'label')}: label of method {name!r} must be a text (the row's name); "
                            f"got {reprlib.repr(entry['label'])}")
            continue
        methods.append((i, name, options, entry.get("label", ""), stages))

    datasets, manifests = [], dataset_manifests()
    for i, entry in enumerate(_entries(data, "datasets", problems, where)):
        entry = {"name": entry} if isinstance(entry, str) else entry
        for key in sorted(set(entry) - DATASET_KEYS):
            problems.append(f"{where('datasets', i, key)}: dataset entry {i + 1} has unknown key {key!r} (allowed: {', '.join(sorted(DATASET_KEYS))})")
        name = str(entry.get("name"))
        if "protocol" in entry and "protocols" in entry:  # else `protocol` was dropped, silently
            problems.append(f"{where('datasets', i, 'protocol')}: dataset {reprlib.repr(name)} gives both protocol and "
                            "protocols; give one (protocols = [...] for several)")
            continue
        wanted = entry.get("protocols", [entry["protocol"]] if "protocol" in entry else [overrides.get("protocol")])
        if not isinstance(wanted, list) or not wanted or not all(isinstance(p, str) or p is None for p in wanted):
            key, kind = ("protocols", "a list of names, e.g. ['vpr-bench']") if "protocols" in entry else ("protocol", "a name")
            problems.append(f"{where('datasets', i, key)}: {key} of dataset {reprlib.repr(name)} must be {kind}; "
                            f"got {reprlib.repr(entry[key])}")
            continue
        if is_path(name):  # a folder's protocols are checked when it is read, making its cells
            datasets.extend((i, name, protocol) for protocol in wanted)
            continue
        if name not in manifests:
            problems.append(f"{where('datasets', i, 'name')}: unknown dataset {reprlib.repr(name)}.{closest_names(name, manifests)}"
                            " Run 'vprbench datasets list'.")
            continue
        known = protocols(manifests[name])
        for protocol in wanted:
            if protocol is not None and protocol not in known and protocol != "default":
                problems.append(f"{where('datasets', i, 'protocols' if 'protocols' in entry else 'protocol')}: dataset {name!r} "
                                f"has no protocol {reprlib.repr(protocol)}; its protocols: {', '.join(known)}")
            else:
                datasets.append((i, name, protocol))

    _raise_problems(origin, problems)
    return PlanEntries(data.get("name", default_name), data.get("description", ""), origin, where,
                       methods, datasets, shared)


def layered_search(planned, given: dict | None):
    """The command line's search over the plan's, as its method options are: for the plan's index (no
    --index, or the same one) its --index-option over the plan's options, the others kept; another
    --index replaces the plan's search, whose options are that index's."""
    if not given:
        return planned
    planned = {"index": planned} if isinstance(planned, str) else planned
    if not isinstance(planned, dict) or not isinstance(planned.get("options") or {}, dict):
        return given  # a malformed plan search is the command line's to replace
    index = given.get("index", planned.get("index", "exact"))
    if index != planned.get("index", "exact"):
        return given
    # the plan's other keys kept, so a wrong one is still named
    return {**planned, "index": index, "options": {**(planned.get("options") or {}), **given.get("options", {})}}


def _entries(data: dict, key: str, problems: list[str], where) -> list:
    entries = data.get(key)
    if not isinstance(entries, list) or not entries:
        problems.append(f"{where('', 0, key)}: the plan needs a non-empty list of {key} ([[{key}]] tables or {key} = [...])")
        return []
    good = []
    for i, entry in enumerate(entries):
        if isinstance(entry, (str, dict)):
            good.append(entry)
        else:
            problems.append(f"{where(key, i, '')}: {key} entry {i + 1} must be a name or a table, got {entry!r}")
    return good
