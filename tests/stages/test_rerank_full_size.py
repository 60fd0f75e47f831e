"""Re-ranking at the real size of the largest dataset vprbench serves: Pitts-250k test, 8,280 queries x
their top 100 of 83,952 database images (the pitts250k_tree fixture, synthetic positions). The global-
descriptor re-rankers (aqe, dba) run on every query over the whole database, and a candidates file of
that size is written and read back. Descriptors are made here: each database image a random unit code
of its own, each query its nearest database image's code, so the exact top 1 is that image (a
positive) and a re-ranker of those candidates must keep Recall@1 at 100."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from vprbench.datasets import load_dataset
from vprbench.search.exact import SearchResult, exact_search
from vprbench.row_sources import ArrayRows
from vprbench.spec import resolve_spec
from vprbench.stages import Candidates, StageContext, create_stage
from vprbench.stages.candidates import read_candidates, write_candidates

QUERIES, DATABASE, DEPTH = 8280, 83952, 100


@pytest.fixture(scope="module")
def full(pitts250k_tree):
    dataset = load_dataset("pitts250k", pitts250k_tree.data)
    truth = dataset.ground_truth
    codes = np.random.default_rng(0).normal(size=(DATABASE, 128))
    codes = (codes / np.linalg.norm(codes, axis=1, keepdims=True)).astype(np.float32)
    _, nearest = cKDTree(truth.database_positions).query(truth.query_positions)
    database, queries = ArrayRows(codes), ArrayRows(codes[nearest])
    found = exact_search(database, queries, DEPTH)
    return dataset, database, queries, found, nearest


class Recorded:
    """A progress reporter that keeps, per task, its description, total and each advance."""

    def __init__(self):
        self.tasks = []

    def add_task(self, description, total=None, **_):
        self.tasks.append({"description": description, "total": total, "advances": []})
        return len(self.tasks) - 1

    def advance(self, task, n=1):
        self.tasks[task]["advances"].append(n)


def recall_at_1(indices, positives) -> float:
    return 100 * float(np.mean([row[0] in set(p.tolist()) for row, p in zip(indices, positives)]))


@pytest.mark.parametrize("stage", ["aqe", "dba"])
def test_expansion_keeps_exact_candidates_first_at_full_size(full, stage):
    dataset, database, queries, found, nearest = full
    assert (len(dataset.database), len(dataset.queries)) == (DATABASE, QUERIES)
    candidates = Candidates(found.indices, found.scores)
    assert candidates.indices.shape == (QUERIES, DEPTH)
    np.testing.assert_array_equal(candidates.indices[:, 0], nearest)  # the oracle's top 1: its own code
    assert recall_at_1(candidates.indices, dataset.positives) == 100.0
    progress = Recorded()
    context = StageContext(dataset=dataset, database=database, queries=queries, progress=progress)
    after = create_stage(stage, {"k": DEPTH}).apply(candidates, context)
    assert after.indices.shape == (QUERIES, DEPTH)
    np.testing.assert_array_equal(after.indices[:, 0], nearest)
    assert recall_at_1(after.indices, dataset.positives) == 100.0
    # a re-ordering of each query's own 100 candidates
    np.testing.assert_array_equal(np.sort(after.indices, 1), np.sort(candidates.indices, 1))
    # progress moves while it works (silent for minutes on larger descriptors), and ends at its total
    (task,) = progress.tasks
    expected = QUERIES if stage == "aqe" else len(np.unique(candidates.indices))
    assert task["total"] == expected == sum(task["advances"])
    assert len(task["advances"]) > 1 and max(task["advances"]) <= 8192


def test_candidates_file_round_trips_at_full_size(full, pitts250k_tree, tmp_path):
    dataset, _, _, found, _ = full
    spec = resolve_spec("hog", dataset, options={"resize": [32, 32]}, cache_dir=tmp_path)
    searched = SearchResult(found.scores, found.indices, {"dim": 1})  # a search's info names its dim (the record's)
    path = write_candidates(tmp_path / "candidates.h5", spec, searched, "images")
    assert 8_000_000 < path.stat().st_size < 11_000_000  # int64 + float32 per candidate, no more
    read = read_candidates(path, spec, QUERIES, DATABASE, DEPTH, "images")
    assert read["k"] == DEPTH
    np.testing.assert_array_equal(read["found"].indices, found.indices)
    np.testing.assert_array_equal(read["found"].scores, found.scores.astype(np.float32))
