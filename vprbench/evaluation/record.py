"""The result record (everything needed to read, compare and repeat one evaluation) and the
results store that keeps one record per run.

Schema: docs/record-schema.md. Store: one JSON file per run under `<cache>/results/`, plus
its per-query arrays in an `.npz` beside it, each written to a temporary name and renamed,
so concurrent writers, kills and full disks never leave a partial or mixed record.
"""
from __future__ import annotations

import hashlib
import io
import json
import os
import platform
import re
import uuid
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import VPRBenchError, os_error_message
from ..fsutil import CacheError, atomic_write
from ..paths import cache_root

SCHEMA = "vprbench-result"
SCHEMA_VERSION = 2  # 1 = the unversioned JSON lines of vprbench 0.1
#: the per-query arrays, in the record and in its .npz
PER_QUERY_FIELDS = ("database_indices", "similarities", "first_positive_rank", "positives")
REQUIRED = ("method", "dataset", "recall", "counts")


# ---------------------------------------------------------------- protocol and dataset identity
def provisional_protocol(name: str, database: int, queries: int, unit: str, radius) -> dict:
    """For a dataset that carries no protocol (one built by hand, outside `load_dataset`): what
    defines it, marked provisional. The leaderboard puts such runs in no benchmark's cell."""
    defining = {"dataset": name, "database": int(database), "queries": int(queries), "unit": unit,
                "radius": None if radius is None else float(radius)}
    digest = hashlib.sha256(json.dumps(defining, sort_keys=True).encode()).hexdigest()[:16]
    return {"name": "provisional", "id": f"{name}:provisional", "hash": digest, "provisional": True, **defining}


def protocol_of(dataset) -> dict:
    """The evaluated dataset's protocol (datasets/protocol.py), else the provisional one."""
    found = getattr(dataset, "protocol", None)
    if found:
        return dict(found)
    gt = dataset.ground_truth
    return provisional_protocol(dataset.name, len(dataset.database), len(dataset.queries), gt.unit, gt.radius)


def benchmark_protocols(name: str) -> dict[str, dict]:
    """Hash -> protocol record of every protocol a benchmark's manifest defines, the default first;
    {} for a name that is no benchmark."""
    from ..datasets import dataset_manifests, protocols

    manifest = dataset_manifests().get(name)
    return {} if manifest is None else {p.hash: p.record() for p in protocols(manifest).values()}


def benchmark_protocol(name: str) -> dict | None:
    """A benchmark's default protocol (the one its manifest names first), or None."""
    return next(iter(benchmark_protocols(name).values()), None)


def dataset_kind(dataset) -> str:
    """'benchmark' (read through a shipped manifest) or 'own' (a folder of the user's own, even
    one whose dataset.toml borrows a benchmark's name)."""
    return "own" if dataset.layout == "own" else getattr(dataset, "kind", None) or "benchmark"


def dataset_fingerprints(dataset, dataset_key: str) -> dict:
    found = {"dataset": dataset_key}
    for part, attribute in (("images", "images_fingerprint"), ("ground_truth", "ground_truth_fingerprint")):
        if callable(getattr(dataset, attribute, None)):
            found[part] = getattr(dataset, attribute)()
    return found


# ---------------------------------------------------------------- provenance and environment
def method_provenance(method) -> dict:
    """`method.provenance()`, completed: a method that does not say where its weights came from
    is 'undeclared' (never official); a method that fits on the database says so."""
    from ..methods import Method

    found = {k: dict(v) if isinstance(v, dict) else v for k, v in (method.provenance() or {}).items()}
    declared = type(method).provenance is not Method.provenance
    found.setdefault("weights", {"source": "none" if declared else "undeclared"})
    if method.needs_fit:
        found.setdefault("vocabulary", {"source": "map"})
        found["vocabulary"].setdefault("fitted_on_evaluated_database", True)
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
def per_query_section(scores: np.ndarray, indices: np.ndarray, correct: np.ndarray, positives) -> dict:
    """What any retrieval metric needs, per query, without descriptors: the top-K database
    indices and similarities, the 1-based rank of the first positive among them (0 = none in the
    top K) and the number of positives the query has in the whole database."""
    indices = np.asarray(indices, dtype=np.int64)
    first = np.where(correct.any(axis=1), correct.argmax(axis=1) + 1, 0)
    return {
        "k": int(indices.shape[1]) if indices.ndim == 2 else 0,
        "database_indices": indices.tolist(),
        "similarities": np.round(np.asarray(scores, dtype=np.float64), 6).tolist(),
        "first_positive_rank": first.tolist(),
        "positives": [int(len(p)) for p in positives],
    }


def result_record(*, method, fingerprint, dataset, dataset_key, ks, scores, indices, positives,
                  descriptor_dim, computed, timings, search=None, context=None) -> dict:
    """The record of one run, from the search's top-K (scores and database indices per query):
    every metric is computed here, from what the record keeps."""
    from .metrics import correct_at, top1_precision_recall

    correct = correct_at(indices, positives)  # (queries, K): once, for every metric below
    section = per_query_section(scores, indices, correct, positives)
    first = np.asarray(section["first_positive_rank"])
    recalls = {k: float(100.0 * np.mean((first >= 1) & (first <= k))) for k in ks}  # all queries count
    pr = top1_precision_recall(scores[:, 0], correct[:, 0])
    summary = dataset.summary()
    described = computed["database"] + computed["queries"]
    extract_s = timings["database_s"] + timings["queries_s"]
    created = datetime.now(timezone.utc)
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "run_id": f"{created:%Y%m%dT%H%M%SZ}-{uuid.uuid4().hex[:12]}",
        "created": created.isoformat(timespec="milliseconds"),  # orders runs, also two in one second
        "method": method.name,
        "method_options": {k: list(v) if isinstance(v, tuple) else v for k, v in method.options.items()},
        "method_settings": _jsonable(getattr(method, "settings", None)),
        "method_fingerprint": fingerprint,
        "needs_fit": bool(method.needs_fit),
        "dataset": dataset.name,
        "dataset_kind": dataset_kind(dataset),
        "dataset_fingerprint": dataset_key,
        "dataset_fingerprints": dataset_fingerprints(dataset, dataset_key),
        "dataset_root": str(Path(dataset.root).resolve()) if dataset.root else None,
        "protocol": protocol_of(dataset),
        "domain": dataset.domain,
        "counts": {
            "database": summary["database"], "queries": summary["queries"],
            "queries_without_positives": summary["queries"] - summary["queries_with_positives"],
            "positive_pairs": summary["positive_pairs"],
        },
        "ground_truth": {"unit": summary["unit"], "radius": summary["radius"], "radius_unit": summary["radius_unit"]},
        "descriptor_dim": descriptor_dim,
        "descriptor_bytes": int(descriptor_dim) * 4,  # float32, as stored and searched
        "recall": {str(k): round(v, 4) for k, v in recalls.items()},
        "auc_pr": round(pr["auc_pr"], 6),
        "recall_at_100_precision": round(pr["recall_at_100_precision"], 6),
        "descriptors_computed": computed,
        "timings": {k: round(v, 4) for k, v in timings.items()},
        "images_per_second": round(described / extract_s, 3) if described and extract_s > 0 else None,
        "top_predictions": np.asarray(indices)[:, : min(ks[-1], 5)].tolist(),  # 0.1's key; per_query has the whole top K
        "provenance": method_provenance(method),
        "search": search or {"index": "exact"},
        **({"context": context} if context else {}),
        **environment(),
        "per_query": section,
    }


def _jsonable(value):
    return None if value is None else json.loads(json.dumps(value, default=str))


# ---------------------------------------------------------------- the results store
def results_dir(cache_dir=None) -> Path:
    return cache_root(cache_dir) / "results"


def results_path(cache_dir=None) -> Path:
    """The JSON-lines file of vprbench 0.1, still read (never written)."""
    return cache_root(cache_dir) / "results.jsonl"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(text))[:60]


def save_result(record: dict, cache_dir=None) -> Path:
    """Store one record as its own file (per-query arrays in an .npz beside it); returns the
    JSON path. Safe with any number of concurrent writers: every run has its own name."""
    folder = results_dir(cache_dir)
    run_id = record.get("run_id") or f"{datetime.now(timezone.utc):%Y%m%dT%H%M%SZ}-{uuid.uuid4().hex[:12]}"
    stem = f"{run_id}-{_slug(record['method'])}-{_slug(record['dataset'])}"
    path = folder / f"{stem}.json"
    summary = {k: v for k, v in record.items() if not k.startswith("_")}
    summary["run_id"] = run_id
    try:
        folder.mkdir(parents=True, exist_ok=True)
        section = record.get("per_query")
        if section and "file" not in section:
            arrays = _per_query_arrays(section)
            buffer = io.BytesIO()
            np.savez_compressed(buffer, **arrays)
            data = buffer.getvalue()
            atomic_write(folder / f"{stem}.npz", data)
            summary["per_query"] = {"file": f"{stem}.npz", "sha256": hashlib.sha256(data).hexdigest(),
                                    "k": section["k"], "queries": len(section["first_positive_rank"]),
                                    "fields": list(PER_QUERY_FIELDS)}
        atomic_write(path, json.dumps(summary, sort_keys=True, indent=1).encode())
    except OSError as error:
        raise VPRBenchError(f"{os_error_message(error, folder)} The result was not stored.") from None
    except CacheError as error:
        raise VPRBenchError(f"{error} The result was not stored.") from None
    return path


#: the name callers of vprbench 0.1 use
append_result = save_result


def _per_query_arrays(section: dict) -> dict[str, np.ndarray]:
    return {
        "database_indices": np.asarray(section["database_indices"], dtype=np.int32).reshape(-1, section["k"]),
        "similarities": np.asarray(section["similarities"], dtype=np.float32).reshape(-1, section["k"]),
        "first_positive_rank": np.asarray(section["first_positive_rank"], dtype=np.int32),
        "positives": np.asarray(section["positives"], dtype=np.int32),
    }


def per_query(record: dict) -> dict[str, np.ndarray] | None:
    """The record's per-query arrays (from the record itself or its .npz), or None when the
    record has none (vprbench 0.1) or its file is missing or damaged (with a warning)."""
    section = record.get("per_query")
    if not section:
        return None
    if "file" not in section:
        return _per_query_arrays(section)
    source = record.get("_source")
    path = Path(source).parent / section["file"] if source else None
    try:
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != section.get("sha256"):
            raise ValueError("its content does not match the record's sha256")
        with np.load(io.BytesIO(data), allow_pickle=False) as found:
            arrays = {name: found[name] for name in PER_QUERY_FIELDS}
    except (OSError, ValueError, KeyError, AttributeError, TypeError) as error:
        warnings.warn(f"Per-query data {path} of run {record.get('run_id')} is unreadable ({error}); "
                      "its statistics and figures are skipped.", stacklevel=2)
        return None
    return arrays


def read_results(cache_dir=None) -> list[dict]:
    """Every stored record, oldest first (vprbench 0.1's results.jsonl included, as schema 1).
    A file that is not a whole vprbench record is skipped with a warning naming it."""
    records = []
    folder = results_dir(cache_dir)
    for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
        try:
            record = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            warnings.warn(f"{path} is not a readable JSON record ({type(error).__name__}); skipped.", stacklevel=2)
            continue
        if _accepted(record, str(path)):
            record["_source"] = str(path)
            records.append(record)
    legacy = results_path(cache_dir)
    if legacy.is_file():
        for number, line in enumerate(legacy.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                warnings.warn(f"{legacy}:{number} is not a JSON record; skipped.", stacklevel=2)
                continue
            if _accepted(record, f"{legacy}:{number}"):
                record.setdefault("schema_version", 1)
                record.setdefault("run_id", f"legacy-{number}")
                record["_source"] = f"{legacy}:{number}"
                records.append(record)
    return sorted(records, key=lambda r: (str(r.get("created", "")), str(r.get("run_id", ""))))


def _accepted(record, where: str) -> bool:
    """A whole record of a schema this version reads; anything else is named and skipped."""
    problem = _problem(record)
    if problem:
        warnings.warn(f"{where} is not a vprbench result record this version reads ({problem}); skipped.", stacklevel=3)
    return problem is None


def _problem(record) -> str | None:
    if not isinstance(record, dict):
        return f"a JSON {type(record).__name__}, not an object"
    missing = [key for key in REQUIRED if key not in record]
    if missing:
        return f"missing {', '.join(missing)}"
    if not isinstance(record["counts"], dict) or not isinstance(record["recall"], dict) \
            or not all(isinstance(v, (int, float)) for v in record["recall"].values()):
        return "counts or recall are not what a record holds"
    version = record.get("schema_version", 1)
    if record.get("schema", SCHEMA) != SCHEMA or not isinstance(version, int) or version > SCHEMA_VERSION:
        return f"schema {record.get('schema')!r} version {version!r}; this vprbench reads {SCHEMA!r} up to {SCHEMA_VERSION}"
    return None
