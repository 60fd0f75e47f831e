"""Database-side augmentation within the memory budget: its augmented rows, a block of rows and its search
of the database all fit, or the run is refused up front naming the budget it needs."""
from __future__ import annotations

import re

import numpy as np
import pytest

from traced import peak_of
from vprbench import VPRBenchError
from vprbench.evaluation.budget import check_run_budget, stage_needs
from vprbench.row_sources import ArrayRows, parse_memory
from vprbench.stages import Candidates
from vprbench.stages.base import StageContext
from vprbench.stages.registry import create_stage


def unit_rows(rng, count: int) -> np.ndarray:
    rows = rng.standard_normal((count, 256)).astype(np.float32)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def searched():
    rng = np.random.default_rng(0)
    database, queries = unit_rows(rng, 2000), unit_rows(rng, 5)
    indices = np.stack([rng.choice(2000, 20, replace=False) for _ in queries]).astype(np.int64)
    return database, queries, Candidates(indices, np.zeros(indices.shape, dtype=np.float32))


def dba(searched, budget: int) -> Candidates:
    database, queries, candidates = searched
    context = StageContext(dataset=None, database=ArrayRows(database), queries=ArrayRows(queries), memory_budget=budget)
    return create_stage("dba", {"k": 20, "n": 5, "alpha": 3.0}).apply(candidates, context)


def test_dba_runs_within_the_budget_it_says_it_needs(searched):
    """The need it names is enough, and the run at it stays within it with the same ranking as with room to
    spare. Blocks were sized without the search beside them, which then refused the budget for a block's
    "queries", or held the augmented rows beyond it."""
    with pytest.raises(VPRBenchError, match=r"Stage 'dba': a memory budget of 4\.0 MB is too small\. It holds the "
                                            r"95 augmented database rows of 256 dims \(97\.3 kB\)") as refused:
        dba(searched, 4_000_000)
    need = parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1))
    roomy = dba(searched, 1 << 30)  # first: a first search's imports are not the stage's
    found, peak = peak_of(lambda: dba(searched, need))
    assert peak <= 1.05 * need, (peak, need)  # and the interpreter's own (threadpoolctl's look at the BLAS)
    np.testing.assert_array_equal(found.indices, roomy.indices)
    np.testing.assert_array_equal(found.scores, roomy.scores)
    found, peak = peak_of(lambda: dba(searched, 8_000_000))
    assert peak <= 8_000_000 and np.array_equal(found.indices, roomy.indices)



def test_the_run_plan_refuses_no_budget_dba_runs_in():
    """Before the search, which images dba augments is unknown: the run's plan counts the images it is sure
    to (one query's k), never more, so the budget the stage names and runs in passes the plan. Counting
    every candidate as another image (8 x 20 here, 20 in truth: the queries share their candidates)
    refused it."""
    rng = np.random.default_rng(1)
    database, queries = rng.standard_normal((500, 2048), dtype=np.float32), rng.standard_normal((8, 2048), dtype=np.float32)
    indices = np.tile(rng.choice(500, 20, replace=False), (8, 1)).astype(np.int64)
    searched = database, queries, Candidates(indices, np.zeros(indices.shape, dtype=np.float32))
    with pytest.raises(VPRBenchError, match="too small") as refused:
        dba(searched, 100_000)
    need = parse_memory(re.search(r"at least (\S+ \S+),", str(refused.value)).group(1))
    stage = create_stage("dba", {"k": 20, "n": 5, "alpha": 3.0})
    [(part, planned)] = stage_needs([stage], ArrayRows(database), ArrayRows(queries), 20)
    assert part == "stage 'dba'" and 0 < planned <= need
    check_run_budget([(part, planned)], need)
    dba(searched, need)
