"""R@1 per domain (indoor, urban, aerial, ...): the radar's axes, each the mean over its datasets,
for the measured official rows and for the paper's reported rows."""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .cells import Board


def domain_datasets() -> dict[str, list[str]]:
    """The datasets each radar axis averages: the paper's in that domain (AnyLoc Fig. 1's axes),
    or, for a domain the paper has none of, every benchmark of that domain in this vprbench."""
    from ..datasets import dataset_manifests
    from .tables import reported

    paper = set(reported()["column"])
    found: dict[str, list[str]] = {}
    for name, manifest in sorted(dataset_manifests().items()):
        found.setdefault(manifest.domain, []).append(name)
    return {domain: [n for n in names if n in paper] or names for domain, names in found.items()}


@dataclass(frozen=True)
class DomainMean:
    """A row's R@1 on a radar axis: over all the axis's datasets (complete), else over those it has."""
    value: float
    datasets: tuple[str, ...]
    complete: bool


def domain_means(values: dict[str, float], axes: dict[str, list[str]]) -> dict[str, DomainMean]:
    """{domain: DomainMean} from {dataset: R@1}; a domain the row has no dataset of is absent."""
    found = {}
    for domain, names in axes.items():
        used = names if all(n in values for n in names) else [n for n in values if _domain_of(n) == domain]
        if used:
            found[domain] = DomainMean(float(np.mean([values[n] for n in used])), tuple(used), used == names)
    return found


def _domain_of(name: str) -> str | None:
    return _domains().get(name)


@functools.lru_cache(maxsize=1)
def _domains() -> dict[str, str]:
    """Each benchmark's domain (the manifests ship with the package: once per process; a board asks per cell)."""
    from ..datasets import dataset_manifests

    return {name: manifest.domain for name, manifest in dataset_manifests().items()}


def domain_averages(board: Board, axes: dict[str, list[str]] | None = None) -> dict[str, dict[str, DomainMean]]:
    """Measured rows like the paper's (Row.like_the_paper) on the benchmarks' default protocols: R@1 per radar axis."""
    axes = domain_datasets() if axes is None else axes
    found = {}
    for row in board.rows:
        values = {column.dataset: cell.recall(1) for column in board.columns
                  if row.like_the_paper and column.kind == "benchmark" and column.default
                  and (cell := board.cell(row, column)) and cell.recall(1) is not None}
        if values:
            found[row.name] = domain_means(values, axes)
    return found


def paper_domain_averages(axes: dict[str, list[str]] | None = None) -> dict[str, dict[str, DomainMean]]:
    from .tables import reported

    axes = domain_datasets() if axes is None else axes
    frame = reported()
    frame = frame[frame["metric"] == "r1"]
    return {row: domain_means(dict(zip(part["column"], part["value"])), axes)
            for row, part in frame.groupby("row", sort=False)}
