"""One representation of a VPR dataset and its ground truth."""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

#: how ground truth says a database image is a positive for a query
UNITS = ("metres", "frames", "positives")


@dataclass
class GroundTruth:
    """Positions (metres or frame indices) with a radius, or explicit positive lists.

    - unit "metres": `database_positions`/`query_positions` are (N, 2) easting/northing (or
      any metric plane); positive when the Euclidean distance is <= radius.
    - unit "frames": positions are (N, 1) frame indices; positive when |i - j| <= radius.
    - unit "positives": `positive_lists[q]` are the database indices positive for query q
      (VPR-Bench style); `radius` documents how the provider made them, if known.

    With unit "metres", `database_zones`/`query_zones` (each position's UTM zone, e.g. "10 north",
    from file names) make a pair positive only within one zone: each zone is its own plane.
    """

    unit: str
    radius: float | None = None
    database_positions: np.ndarray | None = None
    query_positions: np.ndarray | None = None
    positive_lists: list[np.ndarray] | None = None
    database_zones: np.ndarray | None = None
    query_zones: np.ndarray | None = None

    def __post_init__(self):
        if self.unit not in UNITS:
            raise ValueError(f"ground-truth unit must be one of {UNITS}, got {self.unit!r}")
        if self.radius is not None:  # NaN would make no pair positive, silently; a negative one fails deep inside
            from numbers import Real

            if isinstance(self.radius, bool) or not isinstance(self.radius, Real) or not 0 <= self.radius < float("inf"):
                raise ValueError(f"ground-truth radius must be a finite number >= 0 (or None), got {self.radius!r}")
        if self.unit == "positives":
            if not isinstance(self.positive_lists, (list, tuple)):  # text would be read character by character
                raise ValueError(f"unit 'positives' needs positive_lists, a list of index lists; got {self.positive_lists!r}")
        elif self.database_positions is None or self.query_positions is None or self.radius is None:
            raise ValueError(f"unit {self.unit!r} needs database/query positions and a radius")
        if (self.database_zones is None) != (self.query_zones is None):
            raise ValueError("ground-truth zones are given for both database and queries, or for neither")

    def said(self) -> str:
        """'positives within 25 metres', 'positive lists': what counts as a positive, in a few words."""
        return "positive lists" if self.unit == "positives" else f"positives within {self.radius:g} {self.unit}"

    def __repr__(self) -> str:
        """One line: the lists or positions of a large benchmark are not printed whole."""
        try:
            if self.unit == "positives":
                return f"GroundTruth('positives', {len(self.positive_lists)} positive lists)"
            return (f"GroundTruth({self.unit!r}, radius={self.radius:g}, {len(self.database_positions)} database and "
                    f"{len(self.query_positions)} query positions)")
        except (TypeError, ValueError):  # fields set by hand to what no reader makes: the plain repr, never a failing one
            return object.__repr__(self)

    def positives(self) -> list[np.ndarray]:
        """For each query, the sorted int64 indices of its positive database images."""
        if self.unit == "positives":
            return [np.unique(np.asarray(p, dtype=np.int64)) for p in self.positive_lists]
        db = np.asarray(self.database_positions, dtype=np.float64).reshape(len(self.database_positions), -1)
        q = np.asarray(self.query_positions, dtype=np.float64).reshape(len(self.query_positions), -1)
        if self.query_zones is None:
            return _within(db, q, float(self.radius))
        db_zones, q_zones = np.asarray(self.database_zones), np.asarray(self.query_zones)
        found = [np.zeros(0, dtype=np.int64)] * len(q)
        for zone in set(q_zones.tolist()):  # each zone's queries against that zone's database images only
            rows, columns = np.flatnonzero(q_zones == zone), np.flatnonzero(db_zones == zone)
            for row, near in zip(rows, _within(db[columns], q[rows], float(self.radius))):
                found[row] = columns[near]
        return found


def _within(db: np.ndarray, q: np.ndarray, radius: float) -> list[np.ndarray]:
    """For each query, the sorted indices of the database positions within `radius`."""
    if not len(db):
        return [np.zeros(0, dtype=np.int64) for _ in q]
    from sklearn.neighbors import NearestNeighbors

    # the tiny slack keeps a pair at exactly the radius positive despite float rounding
    found = NearestNeighbors().fit(db).radius_neighbors(q, radius=radius + 1e-9, return_distance=False)
    return [np.sort(np.asarray(idx, dtype=np.int64)) for idx in found]


@dataclass
class Dataset:
    """Database and query images (in ground-truth order) plus ground truth and provenance."""

    name: str
    database: list[Path]
    queries: list[Path]
    ground_truth: GroundTruth
    domain: str = ""
    title: str = ""
    citation: str = ""
    licence: str = ""
    root: Path | None = None
    notes: list[str] = field(default_factory=list)
    #: the layout the images were read in (a manifest may accept several)
    layout: str = ""
    #: unit of ground_truth.radius ("metres"/"frames"); for explicit lists, how the provider made them
    radius_unit: str = ""
    #: the evaluation protocol: name, id, hash and what defines it (datasets/protocol.py)
    protocol: dict = field(default_factory=dict)
    #: "benchmark" (a shipped manifest) or "own" (a folder of the user's own)
    kind: str = "benchmark"
    #: how the splits' capture order is known, for sequence matching (datasets/traverse.py)
    sequence_order: str = ""

    def __post_init__(self):
        """A Dataset made by hand: image paths given as text are Paths (else a failure deep inside)."""
        import os

        from ..errors import require

        require(self.name, str, "Dataset's name takes text")
        require(self.ground_truth, GroundTruth, "Dataset's ground_truth takes a vprbench GroundTruth")
        for split in ("database", "queries"):
            paths = getattr(self, split)
            require(paths, (list, tuple), f"Dataset's {split} takes a list of image paths")
            if not all(isinstance(p, Path) for p in paths):  # the readers' lists pass as they are
                for p in paths:
                    require(p, (str, os.PathLike), f"Dataset's {split} takes a list of image paths")
                setattr(self, split, [Path(p) for p in paths])
        if self.root is not None:
            require(self.root, (str, os.PathLike), "Dataset's root takes a folder path, or None")
            self.root = Path(self.root)

    def __repr__(self) -> str:
        """One line, not every image path (a notebook showing a Pitts30k Dataset printed 17,000 of them)."""
        if not isinstance(self.ground_truth, GroundTruth):  # set by hand after it was made
            return object.__repr__(self)
        protocol = self.protocol.get("id") if isinstance(self.protocol, dict) else None
        parts = [repr(self.name), f"{len(self.database)} database", f"{len(self.queries)} queries",
                 self.ground_truth.said()]
        parts += [f"protocol {protocol}"] if protocol else []
        parts += [f"root={str(self.root)!r}"] if self.root is not None else []
        return f"Dataset({', '.join(parts)})"

    @cached_property
    def positives(self) -> list[np.ndarray]:
        gt = self.ground_truth
        if gt.unit != "positives" and not all(np.isfinite(np.asarray(p, dtype=np.float64)).all()
                                               for p in (gt.database_positions, gt.query_positions)):
            from ..errors import VPRBenchError  # the readers name the file; this guards any other source

            raise VPRBenchError(f"Dataset {self.name!r}: its positions under {self.root} hold non-finite numbers "
                                "(NaN or infinity); fix or replace its ground truth.")
        positives = gt.positives()
        if len(positives) != len(self.queries):
            from ..errors import VPRBenchError

            raise VPRBenchError(
                f"Dataset {self.name!r}: ground truth covers {len(positives)} queries "
                f"but {len(self.queries)} query images were found."
            )
        bad = [q for q, p in enumerate(positives) if len(p) and (p.min() < 0 or p.max() >= len(self.database))]
        if bad:
            from ..errors import VPRBenchError

            worst = positives[bad[0]].min() if positives[bad[0]].min() < 0 else positives[bad[0]].max()
            raise VPRBenchError(
                f"Dataset {self.name!r}: ground truth of query {bad[0]} names database image {worst}, outside "
                f"0..{len(self.database) - 1}; the ground-truth file does not match the images."
            )
        return positives

    def summary(self) -> dict:
        pos = self.positives
        return {
            "name": self.name,
            "title": self.title,
            "domain": self.domain,
            "database": len(self.database),
            "queries": len(self.queries),
            "queries_with_positives": int(sum(len(p) > 0 for p in pos)),
            "positive_pairs": int(sum(len(p) for p in pos)),
            "unit": self.ground_truth.unit,
            "radius": self.ground_truth.radius,
            "radius_unit": self.radius_unit or (self.ground_truth.unit if self.ground_truth.unit != "positives" else None),
            # the folder itself, as records and `datasets verify` name it (not the relative path typed)
            "root": str(Path(self.root).resolve()) if self.root else None,
            "layout": self.layout,
        }

    def images_fingerprint(self, cache_dir=None) -> dict[str, str]:
        """Content identity of the images, per split: names and the sha256 of every file
        (memoised in the cache by path, size and mtime)."""
        if "_images_fingerprint" not in self.__dict__:
            from .identity import images_key

            digests, names = self.image_digests(cache_dir), self.image_names()
            self._images_fingerprint = {split: images_key(getattr(self, split), self.root, digests=digests[split],
                                                          names=names[split]) for split in ("database", "queries")}
        return dict(self._images_fingerprint)

    def image_names(self) -> dict[str, list[str]]:
        """The names stores and records use, per split (relative to the root), made once per Dataset:
        the run's stores and its record's dataset identity both need them (0.6 s per split at 92k)."""
        if "_image_names" not in self.__dict__:
            from .identity import image_names

            self._image_names = {split: image_names(getattr(self, split), self.root) for split in ("database", "queries")}
        return self._image_names

    def image_digests(self, cache_dir=None) -> dict[str, list[str]]:
        """sha256 of every image's bytes, per split, taken once per Dataset (memoised in the cache)."""
        if "_image_digests" not in self.__dict__:
            from .identity import content_hashes

            self._image_digests = {split: content_hashes(getattr(self, split), cache_dir)
                                   for split in ("database", "queries")}
        return self._image_digests

    def ground_truth_fingerprint(self) -> str:
        """Identity of what counts as a positive: a change re-scores stored descriptors."""
        h = hashlib.sha256()
        h.update(json.dumps([self.ground_truth.unit, self.ground_truth.radius], default=str).encode())
        for positives in self.positives:
            h.update(len(positives).to_bytes(8, "little"))
            h.update(np.ascontiguousarray(positives, dtype="<i8").tobytes())
        return h.hexdigest()

    def fingerprint(self, cache_dir=None) -> str:
        """Images (content) and ground truth together: what a result was computed on."""
        from ..hashing import canonical_hash

        return canonical_hash({"name": self.name, "images": self.images_fingerprint(cache_dir),
                               "ground_truth": self.ground_truth_fingerprint()})
