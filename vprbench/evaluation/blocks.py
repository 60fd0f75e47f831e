"""Which queries a bootstrap resamples together.

Queries along a traverse, or a few metres apart, are not independent: neighbours look alike and
share positives, so resampling them one by one gives intervals that are too narrow. The units a
bootstrap draws (with replacement) follow from the ground truth and the run's stages, by one rule:

- "blocks": the queries are frames of a traverse (positives within r frames). Circular blocks of
  L consecutive queries (the circular block bootstrap, Politis & Romano 1992) with
  L = max(round(n^(1/3)), 2r + w): n^(1/3) is the rate at which a block should grow with the
  series (Hall, Horowitz & Jing 1995); w is the run's query window, the consecutive queries whose
  descriptors one query's result reads (1; a sequence stage's `length` frames, offline or causal:
  `Stage.query_window`), and r is counted in query steps. Two queries more than 2r + w - 1 apart
  share no query of their windows and no positive of those queries, so a block of 2r + w holds
  what one query's outcome depends on (2r + 1 without a sequence stage). Each resample is
  round(n / L) blocks.
- "places": the queries have metric positions (positives within r metres). Greedy places: in
  query order, each query not yet placed founds a place with every unplaced query within r of
  it (and in its UTM zone, when file names give zones: so queries of one place are at most 2r
  apart). Each resample draws as many places as there are, and the recall is the successes
  over the queries drawn. Chaining "within r of one
  another" into connected components would merge a whole densely sampled route into one unit;
  merging the places a sequence window spans would do the same (consecutive windows overlap), so
  a sequence run keeps the places: its window can reach the neighbouring places along the
  traverse, whose outcomes it then shares, and its intervals can be somewhat narrow (a limit).
- "queries": positive lists with neither frames nor positions: nothing says which queries are
  neighbours, so each query is its own unit (the plain bootstrap). No sequence stage runs there
  (datasets/traverse.py refuses a dataset that is no traverse).

Two runs compared on the same queries draw the same units for both (`shared`): on a traverse the
longer of their blocks, so a sequence run against a single-image run is paired over blocks that
cover the sequence's window.

A record stores its resampling (`Resampling.describe()`), with the place of every query (or the
traverse order of frames not listed in order) in its per-query arrays; the leaderboard derives it
again from the record (its ground truth and its spec's stages) with the same rule, so a stored
block length is never trusted.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

SCHEMES = ("blocks", "places", "queries")
RULE = {
    "blocks": "circular blocks of L consecutive queries, L = max(round(n^(1/3)), 2r + w) with r the positive "
              "radius in query steps and w the span of queries each result reads (1, or a sequence stage window)",
    "places": "greedy places: each query not yet placed, in query order, takes every unplaced query within the "
              "positive radius (a sequence run's window is not covered)",
    "queries": "each query on its own (no order or positions known)",
}


@dataclass(frozen=True, eq=False)
class Resampling:
    scheme: str
    queries: int
    block_length: int = 1
    #: blocks: the queries in traverse order (None: as listed)
    order: np.ndarray | None = None
    #: places: each query's place, 0 .. places - 1
    places: np.ndarray | None = None
    #: the positive radius the units come from, and its unit
    radius: float | None = None
    unit: str = ""
    #: blocks: the radius in query steps, and the run's query window (what block_length came from)
    radius_steps: float | None = None
    window: int = 1

    @property
    def place_count(self) -> int:
        return int(self.places.max()) + 1 if self.places is not None and len(self.places) else 0

    def units(self, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """(sizes (U,), sums (U, c), draws): per unit its query count and the column sums of
        `values` (queries x c) over its queries, and how many units one resample draws."""
        values = np.asarray(values).reshape(len(values), -1).astype(np.int64)
        n = len(values)
        if len(values) != self.queries:
            raise ValueError(f"the resampling is for {self.queries} queries, the values cover {n}")
        if self.scheme == "blocks" and n:
            length = min(self.block_length, n)
            ordered = values if self.order is None else values[self.order]
            wrapped = np.concatenate([ordered, ordered[: length - 1]])
            total = np.concatenate([np.zeros((1, values.shape[1]), np.int64), np.cumsum(wrapped, axis=0)])
            return np.full(n, length), total[length:length + n] - total[:n], max(1, round(n / length))
        if self.scheme == "places" and n:
            count = self.place_count
            sums = np.stack([np.bincount(self.places, weights=column, minlength=count) for column in values.T], axis=1)
            return np.bincount(self.places, minlength=count), sums.astype(np.int64), count
        return np.ones(n, np.int64), values, n

    def key(self) -> str:
        """The units' identity (two resamplings with one key draw the same units)."""
        import hashlib

        found = hashlib.sha256(f"{self.scheme}:{self.queries}:{self.block_length}".encode())
        for array in (self.order, self.places):
            found.update(b"|" + (b"-" if array is None else np.ascontiguousarray(array, dtype="<i8").tobytes()))
        return found.hexdigest()

    def same_as(self, other: "Resampling") -> bool:
        return self.key() == other.key()

    def for_window(self, window: int) -> "Resampling":
        """These units for a run whose query window is `window` (blocks lengthen; places and
        single queries stay)."""
        steps = self.radius_steps if self.radius_steps is not None else self.radius
        if self.scheme != "blocks" or steps is None or window == self.window:
            return self
        return replace(self, block_length=block_length(self.queries, steps, window), window=window)

    def describe(self) -> dict:
        """For the record (and downloads)."""
        found = {"scheme": self.scheme, "rule": RULE[self.scheme], "radius": self.radius, "radius_unit": self.unit or None}
        if self.scheme == "blocks":
            found.update(block_length=self.block_length, blocks_per_resample=max(1, round(self.queries / self.block_length)),
                         ordered_by_frame=self.order is not None)
            if self.window > 1:  # a plain run's description is as before
                found["query_window"] = self.window
        if self.scheme == "places":
            found["places"] = self.place_count
        return found

    def text(self) -> str:
        """What a page says next to an interval."""
        if self.scheme == "blocks":
            covering = f", covering a sequence window of {self.window}" if self.window > 1 else ""
            return f"blocks of {self.block_length} consecutive queries{covering}"
        if self.scheme == "places":
            return f"by place ({self.place_count:,} places of queries within {self.radius:g} m)"
        return "per query"

    def arrays(self) -> dict[str, np.ndarray]:
        """The per-query arrays a record keeps so the same units can be drawn without the dataset."""
        if self.places is not None:
            return {"place": self.places.astype(np.int32)}
        return {"order": self.order.astype(np.int32)} if self.order is not None else {}


def block_length(queries: int, radius_steps: float, window: int = 1) -> int:
    """The rule: max(round(n^(1/3)), 2r + w), at most n."""
    grown = round(queries ** (1 / 3) + 1e-9)
    covered = 2 * int(np.ceil(max(float(radius_steps), 0.0))) + max(int(window), 1)
    return max(1, min(queries, max(grown, covered)))


def query_window(stages) -> int:
    """The run's query window from its stages (a record's spec["stages"]: name and options): 1 plus
    what each stage's window adds. A stage no longer installed counts by its `length` option."""
    from ..loader import plugin_part
    from ..stages.registry import available_stages

    known, window = available_stages(), 1
    for stage in stages if isinstance(stages, (list, tuple)) else ():
        name = stage.get("name") if isinstance(stage, dict) else None
        options = stage.get("options") if isinstance(stage, dict) and isinstance(stage.get("options"), dict) else {}
        if name in known:
            cls = known[name].cls
            with plugin_part(cls, "query_window", f"Stage {name!r}"):
                try:
                    found = cls.query_window(options)
                except ValueError:  # options that never ran (an edited record): the stage's defaults
                    found = cls.query_window({})
        else:
            length = options.get("length")
            found = length if isinstance(length, int) and not isinstance(length, bool) and length > 0 else 1
        window += int(found) - 1
    return window


def record_window(record: dict) -> int:
    """The query window of a stored run: from its spec's stages (the run's identity)."""
    spec = record.get("spec")
    return query_window(spec.get("stages") if isinstance(spec, dict) else None)


def shared(first: Resampling, second: Resampling) -> Resampling | None:
    """The units two runs on the same queries are both drawn by: their own when the same; on a
    traverse blocks in one order, the longer (it covers both runs' windows); else None."""
    if first.same_as(second):
        return first
    if first.scheme == second.scheme == "blocks" and first.queries == second.queries and \
            replace(first, block_length=1).same_as(replace(second, block_length=1)):
        return max((first, second), key=lambda r: r.block_length)
    return None


def place_groups(positions: np.ndarray, radius: float, zones=None) -> np.ndarray:
    """Each query's place (see the module's rule), numbered in order of foundation; with `zones` (UTM
    zones from file names), a place holds queries of one zone, as positives do."""
    from scipy.spatial import cKDTree

    place = np.full(len(positions), -1, dtype=np.int64)
    if not len(positions):
        return place
    positions = np.asarray(positions, dtype=np.float64).reshape(len(positions), -1)
    tree = cKDTree(positions)
    count = 0
    for start in range(0, len(positions), 4096):  # neighbour lists a chunk at a time bound the memory
        near = tree.query_ball_point(positions[start:start + 4096], float(radius) + 1e-9, return_sorted=False)
        for query, found in enumerate(near, start):
            if place[query] >= 0:
                continue
            found = np.asarray(found, dtype=np.int64)
            found = found if zones is None else found[zones[found] == zones[query]]
            place[found[place[found] < 0]] = count
            count += 1
    return place


def scheme_of(unit: str | None, radius_unit: str | None) -> str:
    """Which scheme a ground truth calls for (see the module's rule)."""
    if unit == "frames" or (unit == "positives" and radius_unit == "frames"):
        return "blocks"
    return "places" if unit == "metres" else "queries"


def for_dataset(dataset, window: int = 1) -> Resampling:
    """The resampling of a dataset's queries, from its ground truth, for a run with query window
    `window` (`query_window`)."""
    gt = dataset.ground_truth
    n = len(dataset.queries)
    stated = (getattr(dataset, "protocol", None) or {}).get("ground_truth") or {}
    radius_unit = getattr(dataset, "radius_unit", "") or stated.get("radius_unit") or ("frames" if gt.unit == "frames" else "")
    scheme = scheme_of(gt.unit, radius_unit)
    radius = None if gt.radius is None else float(gt.radius)
    if scheme == "places" and radius is not None and gt.query_positions is not None:
        zones = None if gt.query_zones is None else np.asarray(gt.query_zones)
        places = place_groups(gt.query_positions, radius, zones)
        return Resampling("places", n, places=places, radius=radius, unit="metres")
    if scheme == "blocks" and radius is not None:
        order, step = None, 1.0
        if gt.unit == "frames" and gt.query_positions is not None:
            frames = np.asarray(gt.query_positions, dtype=np.float64).reshape(n, -1)[:, 0]
            sorted_order = np.argsort(frames, kind="stable")
            order = None if np.array_equal(sorted_order, np.arange(n)) else sorted_order
            gaps = np.diff(frames[sorted_order])
            step = float(np.median(gaps[gaps > 0])) if (gaps > 0).any() else 1.0
        return Resampling("blocks", n, block_length(n, radius / step, window), order=order, radius=radius,
                          unit="frames", radius_steps=radius / step, window=window)
    return Resampling("queries", n, radius=radius, unit=str(radius_unit or ""))


def for_record(record: dict, arrays: dict | None) -> Resampling:
    """The resampling of a stored run: the record's ground truth, counts and stages by the same rule,
    the units drawn from its per-query arrays (places, traverse order). Arrays that are not a valid
    place per query or permutation of the queries are ignored: the plain bootstrap is used."""
    n = int((record.get("counts") or {}).get("queries") or 0)
    if arrays is not None and "first_positive_rank" in arrays:
        n = len(arrays["first_positive_rank"])
    # the protocol's ground truth (what its hash covers), completed by the record's
    stated = (record.get("protocol") or {}).get("ground_truth")
    gt = {**(record.get("ground_truth") or {}), **{k: v for k, v in (stated if isinstance(stated, dict) else {}).items()
                                                  if v is not None}}
    radius = gt.get("radius")
    radius = float(radius) if isinstance(radius, (int, float)) and np.isfinite(radius) else None
    scheme = scheme_of(gt.get("unit"), gt.get("radius_unit"))
    arrays = arrays or {}
    if scheme == "places" and radius is not None:
        places = _valid(arrays.get("place"), n, permutation=False)
        if places is not None:
            return Resampling("places", n, places=places, radius=radius, unit="metres")
    if scheme == "blocks" and radius is not None:
        order = _valid(arrays.get("order"), n, permutation=True)
        stated = (record.get("resampling") or {}).get("block_length")
        window = record_window(record)
        length = block_length(n, radius, window) if gt.get("unit") != "frames" else _frames_length(n, stated, radius, window)
        steps = radius if gt.get("unit") != "frames" else None  # frames: the step is not in the record
        return Resampling("blocks", n, length, order=order, radius=radius, unit="frames", radius_steps=steps,
                          window=window)
    return Resampling("queries", n, radius=radius, unit=str(gt.get("radius_unit") or ""))


def _frames_length(n: int, stated, radius: float, window: int) -> int:
    """Frame positions are not in the record, so their query step is not either: the stated length
    is taken when it lies between the rule's two bounds (the n^(1/3) floor and the length with a
    step of one frame), else the longer bound."""
    low, high = block_length(n, 0, window), block_length(n, radius, window)
    if isinstance(stated, int) and not isinstance(stated, bool) and low <= stated <= high:
        return stated
    return high


def _valid(array, n: int, *, permutation: bool) -> np.ndarray | None:
    if array is None:
        return None
    array = np.asarray(array)
    if array.shape != (n,) or array.dtype.kind not in "iu" or (n and (array.min() < 0 or array.max() >= n)):
        return None
    if permutation:
        return array.astype(np.int64) if np.array_equal(np.sort(array), np.arange(n)) else None
    # every place 0 .. G - 1 holds a query (an empty place would be drawn as a unit of no queries)
    return array.astype(np.int64) if np.array_equal(np.unique(array), np.arange(int(array.max()) + 1 if n else 0)) \
        else None
