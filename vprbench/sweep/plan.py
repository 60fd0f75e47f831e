"""Plans: methods (with options) x datasets (with protocols) x K values, as cells.

A plan file (TOML):

    name = "corridor-check"          # optional
    k = [1, 5, 10]                   # optional (default 1 5 10 20)

    [[methods]]
    name = "hog"
    options = { resize = [64, 64] }

    [[methods]]
    name = "dense-vlad"

    [[datasets]]
    name = "corridor"
    protocols = ["vpr-bench"]        # optional (default: the dataset's first protocol)

`methods = ["hog", "dense-vlad"]` and `datasets = ["corridor"]` are accepted too. Every
problem (unknown key, method, option, dataset or protocol) is listed at once, with its line,
before anything runs.
"""
from __future__ import annotations

import hashlib
import json
import re
import tomllib
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

from ..errors import VPRBenchError, closest_names
from ..evaluation.metrics import DEFAULT_KS

PLAN_KEYS = {"name", "description", "k", "methods", "datasets"}
METHOD_KEYS = {"name", "options", "label"}
DATASET_KEYS = {"name", "protocols", "protocol"}
#: options that change where or how fast a cell runs, not what it computes
RUN_OPTIONS = {"device", "batch_size"}


@dataclass(frozen=True, eq=False)
class Cell:
    method: str
    dataset: str
    options: dict = field(default_factory=dict)
    protocol: str | None = None
    ks: tuple[int, ...] = DEFAULT_KS
    label: str = ""

    @property
    def protocol_id(self) -> str:
        """`dataset:protocol` (the default's name filled in); a folder of one's own has 'own'."""
        return _protocol_id(self.dataset, self.protocol)

    def identity(self) -> dict:
        """What the cell computes: the claim key and the match against stored records."""
        options = {k: list(v) if isinstance(v, tuple) else v for k, v in self.options.items()
                   if v is not None and k not in RUN_OPTIONS}
        return {"method": self.method, "options": options, "dataset": self.dataset,
                "protocol": self.protocol_id, "ks": list(self.ks)}

    @property
    def key(self) -> str:
        return hashlib.sha256(json.dumps(self.identity(), sort_keys=True).encode()).hexdigest()[:16]

    def title(self) -> str:
        shown = " ".join(f"{k}={v}" for k, v in sorted(self.identity()["options"].items()))
        method = self.label or (f"{self.method} [{shown}]" if shown else self.method)
        return f"{method} | {self.protocol_id}"


@dataclass
class Plan:
    name: str
    cells: list[Cell]
    description: str = ""


@cache
def _manifests() -> dict:
    """The shipped manifests, read once per process (a plan of many cells asks often)."""
    from ..datasets import dataset_manifests

    return dataset_manifests()


@cache
def _protocol_id(dataset: str, protocol: str | None) -> str:
    from ..datasets import is_path
    from ..datasets.protocol import find_protocol

    if is_path(dataset):
        return f"{Path(dataset).expanduser().resolve().name}:own"
    return find_protocol(_manifests()[dataset], protocol).id


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


def read_plan(path: str | Path, *, device: str | None = None) -> Plan:
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as error:
        raise VPRBenchError(f"Cannot read plan {path}: {error}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise VPRBenchError(f"Plan {path} is not valid TOML: {error}") from None
    return build_plan(data, str(path), _line_index(text), device=device, default_name=path.stem)


def build_plan(data: dict, origin: str, lines: dict | None = None, *, device: str | None = None,
               default_name: str = "plan") -> Plan:
    """Cells of a plan given as a dict; raises one error listing every problem."""
    from ..datasets import is_path
    from ..datasets.protocol import protocols
    from ..methods import available_methods

    lines = lines or {}
    problems: list[str] = []

    def where(section: str, index: int, key: str) -> str:
        line = lines.get((section, index, key)) or lines.get((section, index, "")) or lines.get(("", 0, section))
        return f"{origin}:{line}" if line else origin

    for key in sorted(set(data) - PLAN_KEYS):
        problems.append(f"{where('', 0, key)}: unknown key {key!r}{closest_names(key, PLAN_KEYS)} (allowed: {', '.join(sorted(PLAN_KEYS))})")
    ks = data.get("k", list(DEFAULT_KS))
    if not isinstance(ks, list) or not ks or not all(isinstance(k, int) and k > 0 for k in ks):
        problems.append(f"{where('', 0, 'k')}: k must be a list of positive whole numbers, got {ks!r}")
        ks = list(DEFAULT_KS)

    methods, known_methods = [], available_methods()
    for i, entry in enumerate(_entries(data, "methods", problems, where)):
        entry = {"name": entry} if isinstance(entry, str) else entry
        for key in sorted(set(entry) - METHOD_KEYS):
            problems.append(f"{where('methods', i, key)}: method entry {i + 1} has unknown key {key!r} (allowed: {', '.join(sorted(METHOD_KEYS))})")
        name = entry.get("name")
        if name not in known_methods:
            problems.append(f"{where('methods', i, 'name')}: unknown method {name!r}.{closest_names(str(name), known_methods)}"
                            " Run 'vprbench methods list'.")
            continue
        options = dict(entry.get("options", {}))
        accepted = known_methods[name].options()
        if device is not None and "device" in accepted:
            options.setdefault("device", device)
        for option in sorted(set(options) - set(accepted)):
            problems.append(f"{where('methods', i, 'options')}: method {name!r} does not take option {option!r}."
                            f"{closest_names(option, accepted)} (It accepts: {', '.join(accepted) or 'none'}.)")
        methods.append((name, {k: tuple(v) if isinstance(v, list) else v for k, v in options.items()}, entry.get("label", "")))

    datasets, manifests = [], _manifests()
    for i, entry in enumerate(_entries(data, "datasets", problems, where)):
        entry = {"name": entry} if isinstance(entry, str) else entry
        for key in sorted(set(entry) - DATASET_KEYS):
            problems.append(f"{where('datasets', i, key)}: dataset entry {i + 1} has unknown key {key!r} (allowed: {', '.join(sorted(DATASET_KEYS))})")
        name = str(entry.get("name"))
        wanted = entry.get("protocols", [entry["protocol"]] if "protocol" in entry else [None])
        if is_path(name):
            datasets += [(name, None)]
            continue
        if name not in manifests:
            problems.append(f"{where('datasets', i, 'name')}: unknown dataset {name!r}.{closest_names(name, manifests)}"
                            " Run 'vprbench datasets list'.")
            continue
        known = protocols(manifests[name])
        for protocol in wanted:
            if protocol is not None and protocol not in known and protocol != "default":
                problems.append(f"{where('datasets', i, 'protocols' if 'protocols' in entry else 'protocol')}: dataset {name!r} "
                                f"has no protocol {protocol!r}; its protocols: {', '.join(known)}")
            else:
                datasets.append((name, protocol))
    if problems:
        what = "The command line" if origin == "the command line" else f"Plan {origin}"
        raise VPRBenchError(f"{what} has {len(problems)} problem(s); nothing was run:\n  " + "\n  ".join(problems))
    cells = [Cell(method=m, options=o, label=label, dataset=d, protocol=p, ks=tuple(sorted(set(ks))))
             for m, o, label in methods for d, p in datasets]
    return Plan(name=str(data.get("name", default_name)), cells=cells, description=str(data.get("description", "")))


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
