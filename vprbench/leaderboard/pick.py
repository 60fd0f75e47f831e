"""Which of a cell's runs fills it (one run, whole: never one run's R@1 beside another's R@10).

The newest run of the row that reports R@1 and R@5, else the newest. A re-run asking fewer K (`--k 1
5`, served from the store) is the same computation as a deeper run of the row when its top-K lists
are that run's as far as it searched: the deeper run then fills the cell, so a quick re-run does not
blank R@10 and R@20. The proof is by content (the arrays), as the cells' is: a re-run whose lists
differ (other code or libraries) fills the cell, however few K it reports.
"""
from __future__ import annotations

import numpy as np

from ..evaluation.results import per_query

#: the K a cell reports (the terminal, the overview, the downloads)
CELL_KS = (1, 5)
#: the R@K a dataset page shows of a cell (site.dataset_page)
SHOWN_KS = (1, 5, 10, 20)
#: similarities are kept to 6 decimals
SIMILARITY_TOLERANCE = 1e-5


def max_k(record: dict) -> int:
    """How deep the run's R@K can be read: its recorded K, or its per-query lists' depth."""
    ks = [int(k) for k in (record.get("recall") or {}) if str(k).isdigit()]
    return max([(record.get("per_query") or {}).get("k", 0), *ks], default=0)


def shown(record: dict) -> int:
    """How many of the dataset page's R@K the run reports."""
    return sum(k <= max_k(record) for k in SHOWN_KS)


def same_lists(deeper: dict, run: dict) -> bool:
    """`deeper`'s top-K lists (indices and similarities) are `run`'s, as deep as `run` searched."""
    deep, shallow = per_query(deeper), per_query(run)
    if deep is None or shallow is None:
        return False
    (queries, depth), found = shallow["database_indices"].shape, deep["database_indices"].shape
    if found[0] != queries or found[1] < depth:
        return False
    return bool(np.array_equal(deep["database_indices"][:, :depth], shallow["database_indices"]) and
                np.allclose(deep["similarities"][:, :depth], shallow["similarities"], rtol=0,
                            atol=SIMILARITY_TOLERANCE))


def pick(runs: list[dict]) -> dict:
    """The run that fills the cell, of its eligible runs (oldest first)."""
    complete = [r for r in runs if max_k(r) >= max(CELL_KS)]
    chosen = (complete or runs)[-1]
    if shown(chosen) == len(SHOWN_KS):  # nothing deeper to show: no arrays read
        return chosen
    deeper = [(shown(r), i, r) for i, r in enumerate(runs) if shown(r) > shown(chosen) and same_lists(r, chosen)]
    return max(deeper, key=lambda found: found[:2])[2] if deeper else chosen  # most K shown, then newest
