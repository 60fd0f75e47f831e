"""What a run is: the one specification every route evaluates, and the one hash that names it.

A single `vprbench evaluate`, a matrix, a plan, `reproduce`, torchrun and the Python API all
build a `RunSpec` with `resolve_spec` and hand it to `vprbench.evaluation.evaluate`. The spec holds
everything that decides a result:

    method + its resolved options    (preset defaults overridden by the options given)
    dataset + protocol (its hash)    (a benchmark's protocol, or a folder's own)
    search                           (exact / ivf-pq / hnsw and their options)
    stages                           (post-retrieval stages, in order: re-ranking, sequence matching)
    ks, store_dtype

and nothing that cannot change one: `RUN_SETTINGS` (device, batch size, workers, memory
budget, lock timeout) travel beside it in `RunSettings`, as do the data and cache folders.

`canonical_hash` is the one rule that turns a value into a name (JSON with sorted keys and
no spaces, sha256, 16 hex digits); protocols, stores, claims, results and leaderboard rows
are all named by it. `RunSpec.key` is the claim key of a sweep's cell; `RunSpec.row_key`
(the spec without its dataset and K) is the leaderboard's row and, with the protocol hash,
the results folder of a run: results/<protocol hash>/<row key>/<run id>.json.
"""
from __future__ import annotations

import math
import os
from collections.abc import Iterable, Mapping
from numbers import Real
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer

from .errors import VPRBenchError, closest_names, require
from .content_identity import option_identities
from .hashing import canonical_hash
from .methods.objects import created_as
from .paths import folder_path
from .spec_options import given_options, plain, spec_options
from .text import shortened
from .run_settings import RUN_SETTINGS, RunSettings, split_run_settings  # noqa: F401 (how a run goes, beside what it is)

#: version of the spec's shape; a spec from a newer vprbench is refused
SPEC_VERSION = 1
INDEXES = ("exact", "ivf-pq", "hnsw")
STORE_DTYPES = ("float32", "float16")
DEFAULT_KS = (1, 5, 10, 20)


# ---------------------------------------------------------------- the specification
class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    #: fields added later, written (and hashed) only when they hold something: a spec without them
    #: is written as before they existed
    _written_when_any: ClassVar[tuple[str, ...]] = ()

    @model_serializer(mode="wrap")
    def _without_empty_later_fields(self, handler):
        written = handler(self)
        for name in self._written_when_any:
            if not getattr(self, name):
                written.pop(name, None)
        return written


class SearchSpec(_Frozen):
    """How the top K are found: exact, or an approximate faiss index whose shortlist is re-scored exactly."""

    index: Literal["exact", "ivf-pq", "hnsw"] = "exact"
    options: dict[str, Any] = {}

    @property
    def approximate(self) -> bool:
        return self.index != "exact"


class StageSpec(_Frozen):
    """A post-retrieval stage (re-ranking, sequence matching) with its options."""

    name: str
    options: dict[str, Any] = {}
    #: option -> the content of the file it names (`Stage.file_identities`); written only when there is one
    files: dict[str, Any] = {}
    _written_when_any: ClassVar[tuple[str, ...]] = ("files",)

    def identity(self) -> dict:
        """What the stage computes: its name and options, files by content instead of their paths."""
        return {"name": self.name, "options": {k: self.files.get(k, v) for k, v in self.options.items()}}

    def label(self) -> str:
        """'sift-ransac@100', with the options that differ from the stage's defaults: 'aqe@20 [n=3]'. Files
        show by content; weights not at all (they have a mark of their own, as a method's)."""
        from .stages.registry import stage_entry

        try:
            defaults = stage_entry(self.name).cls.Options().model_dump(mode="json")
        except (VPRBenchError, ValidationError):  # a plugin gone, or without defaults: its record still reads
            defaults = {}
        depth = f"@{self.options['k']}" if "k" in self.options else ""
        other = {k: _short(self.files.get(k, v)) for k, v in sorted(self.options.items())
                 if k not in ("k", "weights") and defaults.get(k, object()) != v}
        return f"{self.name}{depth}" + (f" [{' '.join(f'{k}={_show(v)}' for k, v in other.items())}]" if other else "")


class DatasetSpec(_Frozen):
    """Which data: a benchmark by name and protocol, or a folder of one's own (its protocol
    hash covers its images and positions, so the folder's path is not part of the identity)."""

    name: str
    kind: Literal["benchmark", "own", "given"]
    protocol: str
    protocol_id: str
    protocol_hash: str
    #: the folder of one's own data (absolute); None for a benchmark
    path: str | None = None


class RunSpec(_Frozen):
    """What one run computes, every part resolved and checked (frozen): made by `resolve_spec` or
    `spec_for`, run by `evaluate`. `key` names the run, `row_key` its leaderboard row (docs/runs.md)."""
    version: int = SPEC_VERSION
    method: str
    #: the method's options: preset defaults overridden by those given (run settings left out)
    options: dict[str, Any]
    #: the options given on top of the preset (what a leaderboard label shows)
    given: dict[str, Any] = {}
    #: option -> "sha256:<hex>" for options that name a file (a file is identified by its bytes), or
    #: "protocol:<hash>" for a vocabulary fitted on a benchmark
    files: dict[str, str] = {}
    #: option -> the content of what it named in the cache when the spec was made (an AnyLoc vocabulary
    #: named "urban" or "domain": Method.cached_identities): in the run's key, not its row's
    found: dict[str, str] = {}
    _written_when_any: ClassVar[tuple[str, ...]] = ("found",)
    #: the options as written where `given` leaves some out (at the value they have anyway, e.g. a layer
    #: the preset's moves to): the method is made from these, so it notes nothing the user chose. Not
    #: part of the run (its identity, its JSON)
    written: dict[str, Any] = Field(default={}, exclude=True, repr=False)
    dataset: DatasetSpec
    search: SearchSpec = SearchSpec()
    stages: tuple[StageSpec, ...] = ()
    ks: tuple[int, ...] = DEFAULT_KS
    store_dtype: Literal["float32", "float16"] = "float32"

    @field_validator("version")
    @classmethod
    def _known_version(cls, version: int) -> int:
        if version > SPEC_VERSION:
            raise ValueError(f"spec version {version} is from a newer vprbench (this one reads up to {SPEC_VERSION}); "
                             "upgrade vprbench")
        return version

    # ------------------------------------------------------------ identity
    def method_identity(self) -> dict:
        """What the method computes: name and options, files by content."""
        return {"method": self.method, "options": {k: self.files.get(k, v) for k, v in self.options.items()}}

    def row_identity(self) -> dict:
        """Everything but the dataset and K: a leaderboard row."""
        return {"version": self.version, **self.method_identity(), "search": self.search.model_dump(),
                "stages": [s.identity() for s in self.stages], "store_dtype": self.store_dtype}

    def identity(self) -> dict:
        found = {"found": self.found} if self.found else {}  # a run without any keeps its key
        return {**self.row_identity(), **found, "protocol": self.dataset.protocol_hash, "ks": list(self.ks)}

    @property
    def key(self) -> str:
        """The run's name: a sweep's claim key; two specs with one key compute the same thing."""
        return canonical_hash(self.identity())

    @property
    def row_key(self) -> str:
        return canonical_hash(self.row_identity())

    # ------------------------------------------------------------ for people
    def label(self) -> str:
        """The method and the options given on top of its preset, e.g. 'hog [resize=64x64]'."""
        shown = {k: v for k, v in self.given.items() if k != "weights"}  # weights have a mark of their own
        label = f"{self.method} [{' '.join(f'{k}={_show(v)}' for k, v in sorted(shown.items()))}]" if shown else self.method
        return " + ".join([label, *(stage.label() for stage in self.stages)])

    def title(self) -> str:
        marks = self.marks()
        shown = f"{self.label()} ({', '.join(marks)})" if marks else self.label()
        return f"{shown} | {self.dataset.protocol_id}"

    def marks(self) -> list[str]:
        """What sets the run apart from an exact float32 one (a row of its own on the board)."""
        return ([f"{self.search.index} search"] if self.search.approximate else []) + \
            ([f"{self.store_dtype} store"] if self.store_dtype != "float32" else [])

    def to_json(self) -> dict:
        return plain(self.model_dump())

    @classmethod
    def from_json(cls, data, origin: str = "the spec") -> "RunSpec":
        try:
            return cls.model_validate(data)
        except ValidationError as error:
            problem = error.errors()[0]
            where = ".".join(str(p) for p in problem["loc"]) or "it"
            raise VPRBenchError(f"{origin} is not a vprbench run specification ({where}: {problem['msg']}).") from None


def _short(value):
    """A file's content identity, shortened for a label: 'sha256:1a2b3c4d'."""
    return value[:15] if isinstance(value, str) and value.startswith("sha256:") else value


def _show(value) -> str:
    """An option's value in a label, on one line: a line break from a value is written out ('\\n'),
    so a label cannot print a line of its own (a forged 'ok' in `results verify`); the terminal
    and the pages write out the other control characters (text.literal, escape.text)."""
    shown = "x".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)
    return shown.replace("\n", "\\n")


# ---------------------------------------------------------------- the resolver
def resolve_spec(method: str, dataset, *, options: dict | None = None, protocol: str | None = None,
                 search: SearchSpec | dict | str | None = None, stages=(), ks=None, store_dtype: str = "float32",
                 data_dir=None, cache_dir=None) -> RunSpec:
    """The spec of one run, every part checked now (not when it runs).

    `options` are the method options given, already layered by the caller (command line over
    plan entry); the method's preset fills in the rest (explicit option > preset > default).
    Run settings (device, batch size, ...) are refused among them: they are not part of the
    spec, pass them in `RunSettings` (`split_run_settings` parts a plan entry's). `dataset` is a
    benchmark name, a folder of one's own, or a `Dataset` already loaded (its protocol is used).
    """
    from .methods.base import Method
    from .methods.checks import plain_options
    from .methods.registry import method_entry

    if isinstance(method, Method):
        raise VPRBenchError(f"resolve_spec takes a method's name; for the method object {method.name or method!r} "
                            "already created, use vprbench.spec.spec_for(method, dataset).")
    require(method, str, "resolve_spec's method takes a method's name, e.g. 'hog' (see 'vprbench methods list')")
    data_dir, cache_dir = folder_path(data_dir, "data_dir"), folder_path(cache_dir, "cache_dir")
    entry = method_entry(method)
    method = entry.name  # as registered (NFC), however it was typed
    written, given = given_options(options), given_options(options, method)
    settings = split_run_settings(options)[1]
    if settings:  # else evaluate(spec) would run without them, on the default device
        name = next(iter(settings))
        raise VPRBenchError(f"{name} is a run setting, not part of a run's spec: pass it to evaluate as "
                            f"vprbench.spec.RunSettings({name}={settings[name]!r}), not in resolve_spec's options.")
    accepted = [o for o in entry.options() if o not in RUN_SETTINGS]
    unknown = sorted(set(given) - set(accepted))
    if unknown:
        hint = closest_names(unknown[0], accepted)
        raise VPRBenchError(f"Method {method!r} does not take option(s) {', '.join(unknown)}.{hint} "
                            f"It accepts: {', '.join(accepted) or 'none'}.")
    given, written = plain_options(method, given), plain_options(method, written)
    if isinstance(stages, (str, dict, StageSpec)):  # one stage, not a list of its characters or keys
        stages = [stages]
    require(stages or (), (list, tuple), "stages takes a list of stages, e.g. ['aqe'] or [{'name': 'sift-ransac', 'k': 100}]")
    ks, stages = check_ks(ks), tuple(resolve_stage(s) for s in stages or ())
    from .search.approximate import searched_to
    from .stages.run import check_stage_chain

    check_stage_chain(stages, ks)
    depth = max([ks[-1], *(s.options["k"] for s in stages if isinstance(s.options.get("k"), int))])  # re-rankers' k
    data = resolve_dataset(dataset, protocol, data_dir, cache_dir)
    if getattr(entry.factory, "dataset_option", None) in given:  # naming the dataset evaluated: as unset
        given = entry.without_defaults(given, data.name)
    merged = spec_options(method, given)
    search = searched_to(resolve_search(search), depth)
    from .evaluation.retrieve import check_compare

    check_compare(method, entry.compare, search.index, search.options)  # with a plan's other problems, not when it runs
    if data.kind == "benchmark":  # a benchmark that is no traverse is refused before its data is needed
        from .datasets.traverse import require_traverse_manifest
        from .stages.registry import stage_entry

        for stage in stages:
            if stage_entry(stage.name).cls.track == "sequence":
                require_traverse_manifest(data.name, f"Sequence stage {stage.name!r}")
    return RunSpec(method=method, options=merged, given=given, written={} if written == given else written,
                   files=option_identities(method, merged, cache_dir),
                   found=entry.cached_identities(merged, data.name, cache_dir),
                   search=search,
                   dataset=data, stages=stages, ks=ks, store_dtype=_choice("--store-dtype", store_dtype, STORE_DTYPES))


def spec_for(method, dataset, **parts) -> RunSpec:
    """The spec of evaluating an already created method (its name and the options it was given)
    on `dataset` (a name, a folder or a `Dataset`): the Python API's way to `resolve_spec`."""
    name = created_as(method)  # first: it checks the attributes read here
    if parts.get("cache_dir") is None:  # what the spec finds by name (spec.found) is what the method itself resolves
        parts["cache_dir"] = getattr(method, "cache_dir", None)
    return resolve_spec(name, dataset, options=dict(getattr(method, "options", {}) or {}), **parts)


def resolve_dataset(dataset, protocol: str | None = None, data_dir=None, cache_dir=None) -> DatasetSpec:
    """A benchmark's protocol comes from its manifest (no data needed); a folder of one's own is
    read (positions, radius, image identities) to name its protocol."""
    from .datasets import Dataset, dataset_manifest, find_protocol, is_path, load_dataset

    if isinstance(dataset, DatasetSpec):  # resolved already (a plan's folder, read once for all its cells)
        return dataset
    if isinstance(dataset, Dataset):
        from .evaluation.identity import check_loaded_protocol, protocol_of

        found = protocol_of(dataset)
        check_loaded_protocol(dataset, found, protocol)  # else a protocol asked of it would be dropped, unsaid
        return DatasetSpec(name=dataset.name, kind="own" if found["name"] == "own" else
                           ("benchmark" if dataset.kind == "benchmark" and not found.get("provisional") else "given"),
                           protocol=found["name"], protocol_id=found["id"], protocol_hash=found["hash"],
                           path=str(Path(dataset.root).resolve()) if dataset.root and found["name"] == "own" else None)
    require(dataset, (str, os.PathLike), "resolve_spec's dataset takes a dataset's name (see 'vprbench datasets "
                                         "list'), the path of a folder of your own or a Dataset")
    name = os.fspath(dataset)
    if is_path(name):
        own = load_dataset(name, data_dir, protocol=protocol, cache_dir=cache_dir)
        return DatasetSpec(name=own.name, kind="own", protocol=own.protocol["name"], protocol_id=own.protocol["id"],
                           protocol_hash=own.protocol["hash"], path=str(Path(name).expanduser().resolve()))
    chosen = find_protocol(dataset_manifest(name), protocol)
    return DatasetSpec(name=name, kind="benchmark", protocol=chosen.name, protocol_id=chosen.id,
                       protocol_hash=chosen.hash)


def resolve_search(search) -> SearchSpec:
    if isinstance(search, SearchSpec):  # checked and written as its table is: else a default written out was
        search = search.model_dump()    # another run, an option the index does not take kept in its identity
    if search is None or isinstance(search, str):
        search = {"index": search or "exact"}
    if not isinstance(search, dict):
        raise VPRBenchError(f"search must be a table such as {{index = \"hnsw\"}}, got {search!r}.")
    unknown = sorted(set(search) - {"index", "options"})
    if unknown:
        raise VPRBenchError(f"search takes index and options, not {', '.join(unknown)}.")
    index = _choice("--index", search.get("index", "exact"), INDEXES)
    options = search.get("options") or {}
    if not isinstance(options, dict):
        raise VPRBenchError(f"Search options must be a table of name = value, got {options!r}.")
    if index == "exact" and options:
        raise VPRBenchError(f"Exact search takes no index options; got {', '.join(sorted(options))}: drop them, or "
                            "choose an approximate index (--index ivf-pq or hnsw; in a plan, search.index).")
    if index != "exact":
        from .search.approximate import DEFAULTS, check_options

        check_options(index, options)
        # a fixed default written out is the same search (shortlist's default depends on the data: kept)
        options = {k: v for k, v in options.items() if k == "shortlist" or DEFAULTS.get(k, object()) != v}
    return SearchSpec(index=index, options=plain(options))


def resolve_stage(stage) -> StageSpec:
    """A stage by name (`"aqe"`), as a table (`{name = "sift-ransac", options = {k = 100}}` or with
    the options beside the name), or a StageSpec: its options validated by the stage's own
    Options model and stored resolved (defaults filled in), so one stage has one identity."""
    from .loader import plugin_part
    from .stages.registry import stage_entry, stage_options

    if isinstance(stage, StageSpec):
        name, options = stage.name, dict(stage.options)
    elif isinstance(stage, str):
        name, options = stage, {}
    elif isinstance(stage, dict):
        name, table = stage.get("name"), stage.get("options")
        table = {} if table is None else table
        if not isinstance(name, str):
            raise VPRBenchError(f"A stage needs a name, e.g. {{name = \"sift-ransac\", k = 100}}; got {stage!r}.")
        if not isinstance(table, Mapping):  # dict() of a string or a list would be a traceback or read it as pairs
            raise VPRBenchError(f"Stage {name!r}: options must be a table of option = value, e.g. {{name = \"{name}\", "
                                f"options = {{k = 100}}}}; got {shortened(repr(table))}.")
        beside = {k: v for k, v in stage.items() if k not in ("name", "options")}
        twice = [k for k in beside if k in table and table[k] != beside[k]]
        if twice:  # else the one beside the name silently replaced the other
            raise VPRBenchError(f"Stage {name!r}: option {twice[0]} is given twice, {shortened(table[twice[0]])} in "
                                f"options and {shortened(beside[twice[0]])} beside the name; give it once.")
        options = {**table, **beside}
    else:
        raise VPRBenchError(f"A stage is a name or a table with a name, got {stage!r}.")
    validated, entry = stage_options(name, options), stage_entry(name)  # its name as registered (NFC)
    with plugin_part(entry.cls, "file_identities", f"Stage {entry.name!r}"):
        files = entry.cls.file_identities(validated)
    return StageSpec(name=entry.name, options=plain(validated.model_dump(mode="json")), files=plain(files))


def check_ks(ks) -> tuple[int, ...]:
    """K values for Recall@K: whole numbers >= 1, sorted, each once (their upper bound is the
    database size, checked when the data is read)."""
    if ks is None:
        return DEFAULT_KS
    if isinstance(ks, (Mapping, bytes)) or not isinstance(ks, (Real, str, Iterable)):
        raise VPRBenchError(f"--k (ks) takes whole numbers >= 1 in a list, e.g. [1, 5, 10]; got {shortened(repr(ks))}.")
    values = [ks] if isinstance(ks, (Real, str)) else list(ks)
    found = []
    for value in values:
        for part in str(value).split(","):
            try:
                number = float(part)
            except ValueError:
                number = math.nan
            if not math.isfinite(number) or number != int(number) or number < 1 or isinstance(value, bool):
                raise VPRBenchError(f"--k (ks) takes whole numbers >= 1 (e.g. --k 1 5 10), got {shortened(' '.join(map(str, values)))}.")
            found.append(int(number))
    if not found:
        raise VPRBenchError("--k (ks) needs at least one value, e.g. --k 1 5 10.")
    return tuple(sorted(set(found)))


def _choice(option: str, value, choices) -> str:
    if value not in choices:
        raise VPRBenchError(f"{option} takes one of {', '.join(choices)}; got {value!r}.")
    return value
