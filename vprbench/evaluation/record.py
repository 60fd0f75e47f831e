"""The result record: everything needed to read, compare and repeat one evaluation, typed.

`result_record` builds it from a search's top K; `Record` validates it (on write and on every
read), and `upgrade` turns a record of an older schema into the current one in memory (the
file is never rewritten). Schema: docs/record-schema.md.
"""
from __future__ import annotations

import io
import re
import uuid
from datetime import datetime, timezone
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import VPRBenchError
from ..spec import RUN_SETTINGS, RunSpec
from ..spec_options import plain
from .identity import dataset_fingerprints, dataset_kind, fingerprint_of, protocol_of
from .provenance import environment, method_provenance, origins

SCHEMA = "vprbench-result"
SCHEMA_VERSION = 3  # 2 = vprbench 0.2 (no spec), 1 = the JSON lines of 0.1 (no longer read)
#: the per-query arrays, in the record and in its .npz
PER_QUERY_FIELDS = ("database_indices", "similarities", "first_positive_rank", "positives")
#: per-query arrays kept when the dataset has them: the bootstrap's units (evaluation/blocks.py)
UNIT_FIELDS = ("place", "order")
#: per-query arrays kept only where they apply: the units, and `all_zero` (1 for a query whose descriptor
#: is all zero: a failure at every K, search.AllZero) when a query is
OPTIONAL_FIELDS = (*UNIT_FIELDS, "all_zero")


# ---------------------------------------------------------------- the typed record
# Numbers the leaderboard shows and computes with: strict, so a string, a bool or a list in a
# record is refused at read (its file named) instead of failing a publish of every record.
#: a count or a size: a whole number >= 0 that fits an int64 (as arrays and floats compute with it)
Count = Annotated[int, Field(strict=True, ge=0, le=2**63 - 1)]
#: a measured amount (seconds, images per second, bytes per image): finite, >= 0, at most 1e12 (no run
#: measures more; a figure's log axis cannot span to near the float maximum); an int is one too
Amount = Annotated[float, Field(strict=True, ge=0, le=1e12, allow_inf_nan=False)]
Fraction = Annotated[float, Field(strict=True, ge=0, le=1, allow_inf_nan=False)]
Percent = Annotated[float, Field(strict=True, ge=0, le=100, allow_inf_nan=False)]
#: when a run was made, as vprbench writes it: UTC, ISO 8601 ('2026-12-07T09:08:46.045+00:00')
_UTC_TIME = re.compile(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d(?:\.\d{1,6})?\+00:00")


def _utc_time(value: str) -> str:
    """`created` as vprbench writes it. Runs are ordered by this text (the newest fills its cell), so one that
    is no such time ('<b>', 'z', another offset) sorted after every real run and kept its cell forever."""
    try:
        datetime.fromisoformat(value)  # a real date and time, not month 13
    except ValueError:
        value = ""
    if not _UTC_TIME.fullmatch(value):
        raise ValueError("should be a UTC time as vprbench writes it, e.g. '2026-12-07T09:08:46.045+00:00'")
    return value


def _numbers(model: type[BaseModel]) -> AfterValidator:
    """A section (a dict) whose numbers `model` names are checked, kept as written (no key added);
    a ValueError naming the first number at fault otherwise."""

    def check(data: dict) -> dict:
        try:
            model.model_validate(data)
        except ValidationError as error:
            problem = error.errors()[0]
            raise ValueError(f"{'.'.join(str(p) for p in problem['loc'])}: {problem['msg']}") from None
        return data

    return AfterValidator(check)


class StageCost(BaseModel):
    """The numbers of one stage's cost (stages/run.py), each optional; other keys are kept."""

    model_config = ConfigDict(extra="allow")

    candidates_in: Count | None = None
    ceiling_recall: Percent | None = None
    ms_per_query: Amount | None = None
    seconds: Amount | None = None
    stored_bytes_per_database_image: Amount | None = None
    peak_rss_bytes: Count | None = None
    peak_rss_growth_bytes: Count | None = None
    features_computed: Count | None = None


class Hardware(BaseModel):
    """The numbers of the machine a run was on (`environment`), each optional; other keys are kept."""

    model_config = ConfigDict(extra="allow")

    cpu_count: Count | None = None
    memory_gib: Amount | None = None


class PerQuerySummary(BaseModel):
    """The sizes a record states of its per-query section (in the record or its .npz)."""

    model_config = ConfigDict(extra="allow")

    k: Count | None = None
    queries: Count | None = None


#: optional numbers left out of a validated record when it does not have them (readers test `in`)
OPTIONAL_NUMBERS = ("descriptor_dim", "descriptor_bytes", "images_per_second", "auc_pr", "max_f1",
                    "recall_at_100_precision", "descriptors_computed", "timings", "stages", "hardware")


class Record(BaseModel):
    """What every reader relies on; other keys are kept as they are."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)

    schema_: Literal["vprbench-result"] = Field(SCHEMA, alias="schema")
    schema_version: int
    run_id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
    created: Annotated[str, Field(strict=True), AfterValidator(_utc_time)]
    method: str
    dataset: str
    dataset_kind: Literal["benchmark", "own", "given"]
    protocol: dict[str, Any]
    counts: dict[str, Count]
    recall: dict[str, Percent]
    spec: RunSpec
    spec_key: str
    row_key: str
    per_query: Annotated[dict[str, Any], _numbers(PerQuerySummary)] | None = None
    # None where a writer leaves them out (an imported run has no descriptor size)
    descriptor_dim: Count | None = None
    descriptor_bytes: Count | None = None
    images_per_second: Amount | None = None
    auc_pr: Fraction | None = None
    max_f1: Fraction | None = None
    recall_at_100_precision: Fraction | None = None
    descriptors_computed: dict[str, Count] | None = None
    timings: dict[str, Amount] | None = None
    stages: list[Annotated[dict[str, Any], _numbers(StageCost)]] | None = None
    hardware: Annotated[dict[str, Any], _numbers(Hardware)] | None = None

    @field_validator("schema_version")
    @classmethod
    def _readable(cls, version: int) -> int:
        if version > SCHEMA_VERSION:
            raise ValueError(f"schema version {version} is from a newer vprbench (this one reads up to "
                             f"{SCHEMA_VERSION}): upgrade vprbench to read it")
        if version < SCHEMA_VERSION:
            raise ValueError(f"schema version {version} must be upgraded first")
        return version

    @field_validator("protocol")
    @classmethod
    def _hashed(cls, protocol: dict) -> dict:
        if not isinstance(protocol.get("hash"), str) or not isinstance(protocol.get("id"), str):
            raise ValueError("the protocol has no id and hash")
        return protocol


def validated(data, where: str) -> dict:
    """`data` (a record of any schema this version reads) upgraded and checked; a VPRBenchError
    naming `where` and the first problem otherwise."""
    if not isinstance(data, dict):
        raise VPRBenchError(f"{where} is not a vprbench result record (a JSON {type(data).__name__}, not an object).")
    if data.get("schema", SCHEMA) != SCHEMA:
        raise VPRBenchError(f"{where} is not a vprbench result record (schema {data.get('schema')!r}).")
    version = data.get("schema_version", 1)
    if isinstance(version, int) and not isinstance(version, bool) and version > SCHEMA_VERSION:
        raise VPRBenchError(f"{where}: schema version {version} is from a newer vprbench (this one reads up to "
                            f"{SCHEMA_VERSION}); upgrade vprbench to read it.")
    if isinstance(version, int) and version == 2:
        data = upgrade(data, where)
    try:
        record = Record.model_validate(data)
    except ValidationError as error:
        problem = error.errors()[0]
        field = ".".join(str(p) for p in problem["loc"]) or "the record"
        raise VPRBenchError(f"{where} is not a vprbench result record this version reads ({field}: "
                            f"{problem['msg']}).") from None
    if record.spec.key != record.spec_key or record.spec.row_key != record.row_key:
        raise VPRBenchError(f"{where}: its spec_key/row_key do not match its spec (edited by hand?).")
    out = record.model_dump(by_alias=True, exclude={k for k in OPTIONAL_NUMBERS if k not in record.model_fields_set})
    out["spec"] = record.spec.to_json()
    return out


def upgrade(data: dict, where: str = "the record") -> dict:
    """A schema-2 record (vprbench 0.2) as a schema-3 one: its spec rebuilt from what it recorded,
    and the fingerprints that 0.2 hashed another way recomputed from their parts."""
    from ..spec import DatasetSpec, SearchSpec

    data = dict(data)
    try:
        given = {k: v for k, v in (data.get("method_options") or {}).items() if k not in RUN_SETTINGS}
        merged = {k: v for k, v in (data.get("method_settings") or given).items() if k not in RUN_SETTINGS}
        weights = (data.get("provenance") or {}).get("weights") or {}
        files = {"weights": f"sha256:{weights['sha256']}"} if "weights" in given and weights.get("sha256") else {}
        protocol = dict(data["protocol"])
        kind = data.get("dataset_kind", "own")
        fingerprints = data.get("dataset_fingerprints") or {}
        if {"images", "ground_truth"} <= set(fingerprints):
            data["dataset_fingerprint"] = fingerprint_of(data["dataset"], fingerprints)
        if kind == "own" and protocol.get("name") == "own":
            from ..spec import canonical_hash

            definition = {k: protocol[k] for k in ("dataset", "database", "queries", "ground_truth", "direction")}
            protocol["content"] = data["dataset_fingerprint"]
            protocol["hash"] = canonical_hash({**definition, "content": protocol["content"]})
        if protocol.get("provisional"):
            kind = "given"
        search = data.get("search") or {}
        index = search.get("index", "exact")
        options = {k: v for k, v in (search.get("options") or {}).items()
                   if k in {"nlist", "pq_m", "nprobe", "train_rows", "shortlist", "recall_queries", "seed", "hnsw_m",
                            "ef_construction", "ef_search"}} if index != "exact" else {}
        ks = sorted(int(k) for k in data["recall"])
        spec = RunSpec(method=data["method"], options=plain(merged), given=plain(given), files=files,
                       dataset=DatasetSpec(name=data["dataset"], kind=kind, protocol=protocol["name"],
                                           protocol_id=protocol["id"], protocol_hash=protocol["hash"],
                                           path=data.get("dataset_root") if kind == "own" else None),
                       search=SearchSpec(index=index, options=options), ks=tuple(ks),
                       store_dtype=(data.get("method_fingerprint") or {}).get("store_dtype", "float32"))
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise VPRBenchError(f"{where} is a vprbench 0.2 record that cannot be upgraded ({type(error).__name__}: "
                            f"{error}); rerun that evaluation.") from None
    data.update(schema_version=SCHEMA_VERSION, protocol=protocol, dataset_kind=kind, spec=spec.to_json(),
                spec_key=spec.key, row_key=spec.row_key, upgraded_from=2)
    return data


# ---------------------------------------------------------------- the record
def kept_similarities(scores) -> np.ndarray:
    """The similarities a record keeps (6 decimals), from which its PR metrics are computed too: a
    checker recomputes them from the record alone (near-ties that rounding merges would otherwise
    move R@100%P by a whole query on a small dataset)."""
    return np.round(np.asarray(scores, dtype=np.float64), 6)


def per_query_section(scores: np.ndarray, indices: np.ndarray, correct: np.ndarray, positives) -> dict:
    """What any retrieval metric needs, per query, without descriptors: the top-K database
    indices and similarities, the 1-based rank of the first positive among them (0 = none in the
    top K) and the number of positives the query has in the whole database."""
    from .metrics import first_positive_rank

    indices = np.asarray(indices, dtype=np.int64)
    first = first_positive_rank(correct)
    return {
        "k": int(indices.shape[1]) if indices.ndim == 2 else 0,
        "database_indices": indices.tolist(),
        "similarities": kept_similarities(scores).tolist(),
        "first_positive_rank": first.tolist(),
        "positives": [int(len(p)) for p in positives],
    }


def new_run_id() -> tuple[str, datetime]:
    created = datetime.now(timezone.utc)
    return f"{created:%Y%m%dT%H%M%SZ}-{uuid.uuid4().hex[:12]}", created


def result_record(*, spec: RunSpec, method, fingerprint, dataset, dataset_key: str, ks, scores, indices, positives,
                  descriptor_dim, computed, timings, search=None, context=None, run=None, cache_dir=None,
                  track: str = "single-image", stages: list[dict] | None = None, all_zero=None) -> dict:
    """The record of one run, from the search's top-K (scores and database indices per query):
    every metric is computed here, from what the record keeps. `all_zero` (search.AllZero, None when
    not counted): the all-zero rows, counted; on the track's terms their queries count as failures."""
    from .metrics import correct_at, kept_metrics, recall_at_k, top1_precision_recall

    from .blocks import for_dataset, query_window

    flags = None if all_zero is None else all_zero.failures(track)
    correct = correct_at(indices, positives, flags)  # (queries, K): once, for every metric below
    section = per_query_section(scores, indices, correct, positives)
    if flags is not None and flags.any():
        section["all_zero"] = flags.astype(np.int32).tolist()
    # which queries the bootstrap draws together: blocks also cover a sequence stage's window
    resampling = for_dataset(dataset, query_window([{"name": s.name, "options": s.options} for s in spec.stages]))
    section.update({name: array.tolist() for name, array in resampling.arrays().items()})
    recalls = recall_at_k(np.asarray(section["first_positive_rank"]), ks)
    pr = top1_precision_recall(kept_similarities(scores)[:, 0], correct[:, 0])
    summary = dataset.summary()
    described = computed["database"] + computed["queries"]
    extract_s = timings["database_s"] + timings["queries_s"]
    run_id, created = new_run_id()
    record = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "run_id": run_id,
        "created": created.isoformat(timespec="milliseconds"),  # orders runs, also two in one second
        "spec": spec.to_json(),
        "spec_key": spec.key,
        "row_key": spec.row_key,
        "label": spec.label(),
        "method": method.name,
        "method_options": plain(spec.given),
        # the spec's options, as the store key takes them: a method created with dataset= the evaluated
        # one kept it in its own settings, which the command line's run of the same spec has not
        "method_settings": _jsonable(plain(spec.options)) if getattr(method, "settings", None) is not None else None,
        "method_fingerprint": fingerprint,
        "needs_fit": bool(method.needs_fit),
        "dataset": dataset.name,
        "dataset_kind": spec.dataset.kind,
        "dataset_fingerprint": dataset_key,
        "dataset_fingerprints": dataset_fingerprints(dataset, dataset_key, cache_dir),
        "dataset_root": summary["root"],  # the folder itself, resolved
        "protocol": protocol_of(dataset),
        "domain": dataset.domain,
        "counts": {
            "database": summary["database"], "queries": summary["queries"],
            "queries_without_positives": summary["queries"] - summary["queries_with_positives"],
            "positive_pairs": summary["positive_pairs"],
            **(all_zero.counts() if all_zero is not None else {}),
        },
        "ground_truth": {"unit": summary["unit"], "radius": summary["radius"], "radius_unit": summary["radius_unit"]},
        "resampling": resampling.describe(),
        "decoding": {"orientation": _orientation()},  # how images were turned into pixels
        "descriptor_dim": descriptor_dim,
        # what the map keeps per image: the store's precision (a float16 store halves it; search reads float32)
        "descriptor_bytes": int(descriptor_dim) * np.dtype(spec.store_dtype).itemsize,
        **kept_metrics(recalls, pr),
        "descriptors_computed": computed,
        "served_from_store": described == 0,
        "timings": {k: round(v, 4) for k, v in timings.items()},
        "images_per_second": round(described / extract_s, 3) if described and extract_s > 0 else None,
        "top_predictions": np.asarray(indices)[:, : min(ks[-1], 5)].tolist(),  # 0.1's key; per_query has the whole top K
        "provenance": method_provenance(method, dataset, cache_dir),
        "search": search or {"index": "exact"},
        "track": track,  # single-image, re-ranked or sequence: the leaderboard table it belongs to
        "stages": stages or [],  # each stage's options and cost (ms per query, bytes per database image, memory)
        "run": run or {},  # how it ran (device, batch size, workers, budget, ...): never part of its identity
        **({"context": context} if context else {}),
        **environment(),
        # the distribution (and version) providing the method and each stage: a plugin's, not only vprbench's
        "origins": origins(method.name, [s.name for s in spec.stages]),
        "per_query": section,
    }
    if dataset_kind(dataset) == "own" and record["dataset_kind"] != "own":
        raise VPRBenchError(f"Dataset {dataset.name!r} is a folder of one's own but its spec says "
                            f"{record['dataset_kind']}.")
    return record


def _orientation() -> str:
    from ..images import ORIENTATION

    return ORIENTATION


def _jsonable(value):
    return None if value is None else plain_or_text(value)


def plain_or_text(value):
    import json

    return json.loads(json.dumps(value, default=str))


def per_query_arrays_in(data: bytes, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """The per-query arrays of an .npz file's bytes, read by the one guarded .npz reader (no
    objects, no header claiming more than the file holds, no more than `max_bytes` unpacked:
    default, the reader's own bound); a ValueError saying why not."""
    from ..datasets.layouts.npy import NPZ_MAX_BYTES, npz_members

    # what else they hold is check_kinds' to refuse
    found = npz_members(io.BytesIO(data), kinds="biufUS", max_bytes=max_bytes or NPZ_MAX_BYTES)
    missing = [field for field in PER_QUERY_FIELDS if field not in found]
    if missing:
        raise ValueError(f"it has no {', '.join(missing)} array")
    return {field: found[field] for field in (*PER_QUERY_FIELDS, *OPTIONAL_FIELDS) if field in found}
