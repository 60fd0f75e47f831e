"""Evaluation protocols as data: which images are the database and the queries, and when a
database image is a positive, named, with an id and a content hash.

A dataset manifest names its default protocol in `[protocol]` and its variants in
`[[protocols]]`. A variant is a few operations applied to the `Dataset` a layout reader
returned, in this order (the readers know nothing of protocols):

    tolerance = 10                      # a new radius; for positive lists, with `frames`:
    frames = { database = [0, 1], queries = [0, 10] }   # frame of image i = start + step * i
    exclude_database_folders = ["distractors"]
    select_queries = { names = "msls_val_qImages.npy", index = "msls_val_qIdx.npy" }
    swap = true                         # database <-> queries

The hash covers what defines the protocol (dataset, splits and their counts, excluded
folders, query subset, unit, radius, direction), not its name or prose, so two protocols
with the same hash evaluate the same thing.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import VPRBenchError, closest_names
from .layouts.base import climbs_out
from .layouts.npy import read_npy
from .model import Dataset, GroundTruth

DEFAULT = "default"
#: keys a protocol table may have
KEYS = {"name", "description", "source", "tolerance", "frames", "exclude_database_folders", "select_queries",
        "swap", "database_count", "query_count"}


@dataclass(frozen=True)
class Protocol:
    dataset: str
    name: str = DEFAULT
    description: str = ""
    source: str = ""
    tolerance: float | None = None
    frames: dict | None = None
    exclude_database_folders: tuple[str, ...] = ()
    select_queries: dict | None = None
    swap: bool = False
    #: image counts after the protocol, where a source gives them
    database_count: int | None = None
    query_count: int | None = None
    #: the ground truth the layout yields (from the manifest): unit, radius, radius_unit
    base: dict = field(default_factory=dict)
    #: False for a default protocol: the manifest's counts are checked by load_dataset (a warning)
    enforce_counts: bool = True

    @property
    def id(self) -> str:
        return f"{self.dataset}:{self.name}"

    def definition(self) -> dict:
        """What the protocol evaluates; the hash is taken over exactly this."""
        tolerance = self.tolerance
        return {
            "dataset": self.dataset,
            "database": {"split": "queries" if self.swap else "database", "count": self.database_count,
                         "exclude_folders": sorted(self.exclude_database_folders)},
            "queries": {"split": "database" if self.swap else "queries", "count": self.query_count,
                        "subset": self.select_queries},
            "ground_truth": {
                "unit": "frames" if tolerance is not None and self.base.get("unit") == "positives" else self.base.get("unit"),
                "radius": tolerance if tolerance is not None else self.base.get("radius"),
                "radius_unit": self.base.get("radius_unit") or None,
                "frames": self.frames if tolerance is not None else None,
            },
            "direction": "swapped" if self.swap else "as released",
        }

    @property
    def hash(self) -> str:
        from ..hashing import canonical_hash

        return canonical_hash(self.definition())

    def record(self) -> dict:
        """`dataset.protocol` and the result record's "protocol" section."""
        return {"name": self.name, "id": self.id, "hash": self.hash, "description": self.description,
                "source": self.source, **self.definition()}


def _base(manifest) -> dict:
    return {"unit": manifest.unit, "radius": manifest.radius,
            "radius_unit": manifest.radius_unit or (manifest.unit if manifest.unit != "positives" else "")}


def _make(manifest, table: dict, where: str) -> Protocol:
    unknown = sorted(set(table) - KEYS)
    if unknown:
        raise VPRBenchError(f"Manifest {manifest.name}: {where} has unknown key(s) {unknown}; allowed: {sorted(KEYS)}.")
    values = dict(table)
    values["exclude_database_folders"] = tuple(values.get("exclude_database_folders", ()))
    for key in ("database_count", "query_count"):  # "any": no sourced count, as many as the copy holds
        if values.get(key) == "any":
            values[key] = None
    if values.get("tolerance") is not None and manifest.unit == "positives" and not values.get("frames"):
        raise VPRBenchError(f"Manifest {manifest.name}: {where} changes the tolerance of positive lists; "
                            "it needs `frames` (the frame index of each image) too.")
    return Protocol(dataset=manifest.name, base=_base(manifest), **values)


def protocols(manifest) -> dict[str, Protocol]:
    """Name -> Protocol for a manifest: the default first, then its variants."""
    default = dict(manifest.protocol or {})
    default.setdefault("name", DEFAULT)
    default.setdefault("database_count", manifest.database_count)
    default.setdefault("query_count", manifest.query_count)
    found = {default["name"]: dataclasses.replace(_make(manifest, default, "[protocol]"), enforce_counts=False)}
    for number, table in enumerate(manifest.protocols, 1):
        if "name" not in table:
            raise VPRBenchError(f"Manifest {manifest.name}: [[protocols]] entry {number} has no name.")
        if table["name"] in found:
            raise VPRBenchError(f"Manifest {manifest.name}: protocol {table['name']!r} is defined twice.")
        found[table["name"]] = _make(manifest, table, f"protocol {table['name']!r}")
    return found


def find_protocol(manifest, name: str | None) -> Protocol:
    """The named protocol (None = the default), or an error listing those that exist."""
    known = protocols(manifest)
    if name is None or name == DEFAULT:
        return next(iter(known.values()))
    if not isinstance(name, str) or name not in known:  # a list would be unhashable below
        raise VPRBenchError(
            f"Dataset {manifest.name!r} has no protocol {name!r}.{closest_names(name, known)} "
            f"Its protocols: {', '.join(known)} (see 'vprbench datasets info {manifest.name}')."
        )
    return known[name]


def own_protocol(dataset: Dataset, cache_dir=None) -> dict:
    """The protocol of a folder of the user's own: its positions and radius, as read, and the
    content of its images and ground truth (two folders that share a name, counts and radius
    but not their images are two protocols)."""
    gt = dataset.ground_truth
    protocol = Protocol(dataset=dataset.name, name="own", description="the folder's own positions and radius",
                        database_count=len(dataset.database), query_count=len(dataset.queries),
                        base={"unit": gt.unit, "radius": gt.radius, "radius_unit": dataset.radius_unit})
    record = protocol.record()
    record["content"] = dataset.fingerprint(cache_dir)
    from ..hashing import canonical_hash

    record["hash"] = canonical_hash({**protocol.definition(), "content": record["content"]})
    return record


# ---------------------------------------------------------------- applying a protocol
def apply_protocol(dataset: Dataset, protocol: Protocol) -> Dataset:
    """A new Dataset: the protocol's operations applied to what the layout reader returned."""
    database, queries, gt = list(dataset.database), list(dataset.queries), dataset.ground_truth
    radius_unit = dataset.radius_unit
    if protocol.tolerance is not None:
        gt = _with_tolerance(dataset, protocol)
        radius_unit = "frames" if dataset.ground_truth.unit == "positives" else radius_unit
    if protocol.exclude_database_folders:
        keep = [not set(protocol.exclude_database_folders).intersection(_relative(dataset, p).parts[:-1]) for p in database]
        database, gt = [p for p, k in zip(database, keep) if k], _keep_database(gt, np.asarray(keep, bool))
    if protocol.select_queries:
        keep = _query_subset(dataset, queries, protocol)
        queries, gt = [p for p, k in zip(queries, keep) if k], _keep_queries(gt, keep)
    if protocol.swap:
        database, queries, gt = queries, database, _swapped(gt, len(database))
    for split, expected, found in (("database", protocol.database_count, len(database)),
                                   ("query", protocol.query_count, len(queries))):
        if protocol.enforce_counts and expected is not None and expected != found:
            raise VPRBenchError(f"Dataset {dataset.name!r}, protocol {protocol.name!r}: {found} {split} images, "
                                f"the protocol expects {expected}; the data under {dataset.root} is not that release.")
    return dataclasses.replace(dataset, database=database, queries=queries, ground_truth=gt,
                               radius_unit=radius_unit, protocol=protocol.record(), kind="benchmark")


def _relative(dataset: Dataset, path: Path) -> Path:
    return path.relative_to(dataset.root) if dataset.root and path.is_relative_to(dataset.root) else Path(path.name)


def _frames(spec, n: int, what: str) -> np.ndarray:
    try:
        start, step = (float(v) for v in spec)
    except (TypeError, ValueError):
        raise VPRBenchError(f"Protocol frames for the {what} must be [start, step], got {spec!r}.") from None
    return (start + step * np.arange(n, dtype=np.float64)).reshape(-1, 1)


def _with_tolerance(dataset: Dataset, protocol: Protocol) -> GroundTruth:
    gt = dataset.ground_truth
    if gt.unit != "positives":
        return dataclasses.replace(gt, radius=float(protocol.tolerance))
    db = _frames(protocol.frames.get("database"), len(dataset.database), "database")
    q = _frames(protocol.frames.get("queries"), len(dataset.queries), "queries")
    # the frame positions must reproduce the released lists at the released radius
    check = GroundTruth(unit="frames", radius=gt.radius, database_positions=db, query_positions=q).positives()
    released = gt.positives()
    wrong = [i for i, (a, b) in enumerate(zip(check, released)) if not np.array_equal(a, b)]
    if wrong or len(check) != len(released):
        raise VPRBenchError(
            f"Dataset {dataset.name!r}, protocol {protocol.name!r}: the frame positions {protocol.frames} do not "
            f"reproduce the released positives at radius {gt.radius} (query {wrong[0] if wrong else len(check)} "
            "differs); the tolerance cannot be changed this way for this copy."
        )
    return GroundTruth(unit="frames", radius=float(protocol.tolerance), database_positions=db, query_positions=q)


def _keep_database(gt: GroundTruth, keep: np.ndarray) -> GroundTruth:
    if gt.unit != "positives":
        zones = {} if gt.database_zones is None else {"database_zones": np.asarray(gt.database_zones)[keep]}
        return dataclasses.replace(gt, database_positions=np.asarray(gt.database_positions)[keep], **zones)
    new_index = np.cumsum(keep) - 1
    lists = []
    for p in gt.positives():
        p = p[(p >= 0) & (p < len(keep))]
        lists.append(new_index[p[keep[p]]].astype(np.int64))
    return dataclasses.replace(gt, positive_lists=lists)


def _keep_queries(gt: GroundTruth, keep: np.ndarray) -> GroundTruth:
    if gt.unit != "positives":
        zones = {} if gt.query_zones is None else {"query_zones": np.asarray(gt.query_zones)[keep]}
        return dataclasses.replace(gt, query_positions=np.asarray(gt.query_positions)[keep], **zones)
    return dataclasses.replace(gt, positive_lists=[p for p, k in zip(gt.positives(), keep) if k])


def _swapped(gt: GroundTruth, n_database: int) -> GroundTruth:
    if gt.unit != "positives":
        return dataclasses.replace(gt, database_positions=gt.query_positions, query_positions=gt.database_positions,
                                   database_zones=gt.query_zones, query_zones=gt.database_zones)
    inverted: list[list[int]] = [[] for _ in range(n_database)]
    for query, positives in enumerate(gt.positives()):
        for d in positives:
            if 0 <= d < n_database:
                inverted[d].append(query)
    return dataclasses.replace(gt, positive_lists=[np.asarray(p, dtype=np.int64) for p in inverted])


def _read_names(path: Path) -> list[str]:
    if path.suffix == ".npy":
        return [str(v) for v in read_npy(path, "query subset file", "image names").reshape(-1)]
    return [line.strip() for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def _query_subset(dataset: Dataset, queries: list[Path], protocol: Protocol) -> np.ndarray:
    """Queries named in a list file (optionally indexed by a second file), matched by image key:
    the listed path's stem equals the query's stem or one of its '@' fields (UTM-named copies)."""
    spec = protocol.select_queries
    root = dataset.root or Path(".")
    named = [str(spec[k]) for k in ("names", "index") if k in spec]
    if any(climbs_out(name) for name in named):
        raise VPRBenchError(f"Dataset {dataset.name!r}, protocol {protocol.name!r} selects its queries from {named}, "
                            "which are not all paths inside the dataset folder; fix the manifest.")
    files = [root / name for name in named]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise VPRBenchError(
            f"Dataset {dataset.name!r}, protocol {protocol.name!r} selects its queries from {', '.join(missing)}, "
            f"which is missing. {protocol.source or ''} Put the file(s) in {root}.".replace("  ", " ")
        )
    try:
        names = _read_names(files[0])
        if "index" in spec:
            index = read_npy(files[1], "query subset index", "query indices").astype(np.int64).reshape(-1)
            if len(index) and not (0 <= index.min() and index.max() < len(names)):  # a negative index would wrap
                raise IndexError(f"its indices must lie in 0..{len(names) - 1}")
            names = [names[i] for i in index]
    except (OSError, ValueError, IndexError) as error:
        raise VPRBenchError(f"Cannot read the query subset of protocol {protocol.name!r} from {files}: {error}.") from None
    wanted = {Path(n).stem for n in names}
    keep = np.array([Path(q).stem in wanted or bool(wanted.intersection(q.name.split("@"))) for q in queries])
    if keep.sum() != len(wanted):
        raise VPRBenchError(
            f"Dataset {dataset.name!r}, protocol {protocol.name!r}: {len(wanted)} queries are listed in "
            f"{files[0].name} but {int(keep.sum())} of the {len(queries)} query images match them."
        )
    return keep
