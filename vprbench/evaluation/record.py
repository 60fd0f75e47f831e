"""The result record: everything needed to read, compare and repeat one evaluation, typed.

`result_record` builds it from a search's top K; `Record` validates it (on write and on every
read), and `upgrade` turns a record of an older schema into the current one in memory (the
file is never rewritten). Schema: docs/record-schema.md.
"""
from __future__ import annotations

import os
import platform
import uuid
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from .. import __version__
from ..errors import VPRBenchError
from ..spec import RUN_SETTINGS, RunSpec, plain
from .identity import dataset_fingerprints, dataset_kind, fingerprint_of, protocol_of

SCHEMA = "vprbench-result"
SCHEMA_VERSION = 3  # 2 = vprbench 0.2 (no spec), 1 = the JSON lines of 0.1 (no longer read)
#: the per-query arrays, in the record and in its .npz
PER_QUERY_FIELDS = ("database_indices", "similarities", "first_positive_rank", "positives")
#: per-query arrays kept when the dataset has them: the bootstrap's units (evaluation/blocks.py)
OPTIONAL_FIELDS = ("place", "order")


# ---------------------------------------------------------------- the typed record
class Record(BaseModel):
    """What every reader relies on; other keys are kept as they are."""

    model_config = ConfigDict(extra="allow", populate_by_name=True)

    schema_: Literal["vprbench-result"] = Field(SCHEMA, alias="schema")
    schema_version: int
    run_id: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,80}$")
    created: str
    method: str
    dataset: str
    dataset_kind: Literal["benchmark", "own", "given"]
    protocol: dict[str, Any]
    counts: dict[str, int]
    recall: dict[str, float]
    spec: RunSpec
    spec_key: str
    row_key: str
    per_query: dict[str, Any] | None = None

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
    out = record.model_dump(by_alias=True)
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


# ---------------------------------------------------------------- provenance and environment
def method_provenance(method, dataset=None, cache_dir=None) -> dict:
    """`method.provenance()`, completed: a method that does not say where its weights came from
    is 'undeclared' (never official); a method that fits on the database says so, and so does
    one whose post-processor (e.g. PCA-whitening) is fitted on the database's descriptors.

    Summaries for tables: `learnt` names every fitted part (vocabulary, pca, ...), so a method
    with learnt parts is never "nothing learnt" even when its weights source is "none";
    `fitted_on_evaluated_database` is true when any part was fitted on the evaluated database
    (transductive), null when a part does not say, else false. A part fitted on images the method
    names by content (`fitted_image_digests()`, sha256 of each file) is transductive when any of
    them is an image of the evaluated `dataset`, whatever the method says."""
    from ..methods import Method

    found = {k: dict(v) if isinstance(v, dict) else v for k, v in (method.provenance() or {}).items()}
    declared = type(method).provenance is not Method.provenance
    found.setdefault("weights", {"source": "none" if declared else "undeclared"})
    if method.needs_fit:
        found.setdefault("vocabulary", {"source": "map", "fitted_on": "the evaluated database"})
        found["vocabulary"].setdefault("fitted_on_evaluated_database", True)
    if method.postprocessor() is not None and not any(k in found for k in ("pca", "postprocessor")):
        found["postprocessor"] = {"source": "fitted", "fitted_on": "the evaluated database's descriptors",
                                  "fitted_on_evaluated_database": True}
    parts = {k: v for k, v in found.items() if isinstance(v, dict) and "fitted_on_evaluated_database" in v}
    fitted_images = getattr(method, "fitted_image_digests", lambda: {})()  # part -> set of sha256
    if fitted_images and dataset is not None:
        evaluated = {d for split in dataset.image_digests(cache_dir).values() for d in split}
        for part, digests in fitted_images.items():
            shared = len(set(digests) & evaluated)
            if shared and part in parts:
                parts[part].update(fitted_on_evaluated_database=True, evaluated_images_fitted_on=shared)
    for part in parts.values():  # a file says what it is by its bytes when nothing else is known
        if "fitted_on" not in part and part.get("sha256"):
            part["fitted_on"] = f"{part.get('released_as') or 'file'} sha256:{part['sha256']}"
    found["learnt"] = sorted(parts)
    leaks = [v["fitted_on_evaluated_database"] for v in parts.values()]
    found["fitted_on_evaluated_database"] = True if True in leaks else (None if None in leaks else False)
    return found


def environment() -> dict:
    import faiss
    import h5py
    import torch

    versions = {"vprbench": __version__, "python": platform.python_version(), "numpy": np.__version__,
                "torch": torch.__version__, "faiss": faiss.__version__, "h5py": h5py.__version__,
                "git": _git_commit()}
    hardware = {"platform": platform.platform(), "machine": platform.machine(), "cpu": _cpu_name(),
                "cpu_count": os.cpu_count(), "memory_gib": _memory_gib(),
                "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None}
    return {"versions": versions, "hardware": hardware}


def _git_commit() -> str | None:
    """The commit of a vprbench source checkout (None for an installed wheel)."""
    head = Path(__file__).resolve().parents[2] / ".git"
    try:
        if head.is_file():  # a worktree: "gitdir: <path>"
            head = Path(head.read_text().split(":", 1)[1].strip())
        ref = (head / "HEAD").read_text().strip()
        if ref.startswith("ref: "):
            name = ref[5:]
            common = head / "commondir"
            root = (head / common.read_text().strip()).resolve() if common.is_file() else head
            for folder in (head, root):
                if (folder / name).is_file():
                    return (folder / name).read_text().strip()
            packed = root / "packed-refs"
            lines = packed.read_text().splitlines() if packed.is_file() else []
            return next((line.split()[0] for line in lines if line.endswith(" " + name)), None)
        return ref
    except (OSError, IndexError):
        return None


def _cpu_name() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def _memory_gib() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        return None


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
                  track: str = "single-image", stages: list[dict] | None = None) -> dict:
    """The record of one run, from the search's top-K (scores and database indices per query):
    every metric is computed here, from what the record keeps."""
    from .metrics import correct_at, recall_at_k, top1_precision_recall

    from .blocks import for_dataset

    correct = correct_at(indices, positives)  # (queries, K): once, for every metric below
    section = per_query_section(scores, indices, correct, positives)
    resampling = for_dataset(dataset)  # which queries the bootstrap draws together
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
        "method_settings": _jsonable(getattr(method, "settings", None)),
        "method_fingerprint": fingerprint,
        "needs_fit": bool(method.needs_fit),
        "dataset": dataset.name,
        "dataset_kind": spec.dataset.kind,
        "dataset_fingerprint": dataset_key,
        "dataset_fingerprints": dataset_fingerprints(dataset, dataset_key, cache_dir),
        "dataset_root": str(Path(dataset.root).resolve()) if dataset.root else None,
        "protocol": protocol_of(dataset),
        "domain": dataset.domain,
        "counts": {
            "database": summary["database"], "queries": summary["queries"],
            "queries_without_positives": summary["queries"] - summary["queries_with_positives"],
            "positive_pairs": summary["positive_pairs"],
        },
        "ground_truth": {"unit": summary["unit"], "radius": summary["radius"], "radius_unit": summary["radius_unit"]},
        "resampling": resampling.describe(),
        "decoding": {"orientation": _orientation()},  # how images were turned into pixels
        "descriptor_dim": descriptor_dim,
        "descriptor_bytes": int(descriptor_dim) * 4,  # float32, as stored and searched
        "recall": {str(k): round(v, 4) for k, v in recalls.items()},
        "auc_pr": round(pr["auc_pr"], 6),
        "max_f1": round(pr["max_f1"], 6),
        "recall_at_100_precision": round(pr["recall_at_100_precision"], 6),
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
