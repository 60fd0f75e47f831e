"""All-zero descriptors (an image with nothing described) match nothing: such a query counts as a
failure at every K, though the search's tie rule lists database rows 0, 1, ... for it (Corridor's
queries 0-2 have database image 0 among their positives, so they were counted as hits), and the
record and the printed table say how many rows were all zero."""
from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest

from runs import evaluate_method
from vprbench import Method, register_method
from vprbench.evaluation.rescore import Truth, rescore
from vprbench.cli.evaluate import results_table
from vprbench.datasets import load_dataset
from vprbench.errors import VPRBenchError
from vprbench.evaluation import evaluate, per_query, read_results, save_result
from vprbench.evaluation.blocks import for_dataset
from vprbench.evaluation.proof import proven
from vprbench.search.exact import exact_search
from vprbench.methods import create_method
from vprbench.spec import RunSettings, resolve_spec
from vprbench.evaluation.pipeline import export_candidates

#: (folder, frame) of the Corridor images the oracle describes by nothing, as a blank or dark image
BLANK = {("query", 0), ("query", 1), ("query", 2), ("ref", 1)}
NOTE = "3 queries and 1 database image with all-zero descriptors (nothing described; such queries count as failures)"


class Oracle(Method):
    """Knows each Corridor image's frame (its file name): query i is database image i, and database
    images i-2 .. i+2 are its positives. The images in `blank` it describes by an all-zero row."""

    blank: frozenset = frozenset()

    def __init__(self, device: str = "cpu"):
        pass

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}

    def describe(self, images):
        rows = np.zeros((len(images), 128), dtype=np.float32)
        for row, path in zip(rows, images):
            if (Path(path).parent.name, int(Path(path).stem)) not in self.blank:
                row[int(Path(path).stem)] = 1
        return rows


pytestmark = pytest.mark.usefixtures("scratch_methods")  # what a test registers is its own


@pytest.fixture(scope="module")
def corridor(shared_data):
    return load_dataset("corridor", shared_data)


def oracle(name: str, blank) -> Method:
    register_method(name, type(name.title().replace("-", ""), (Oracle,), {"blank": frozenset(blank)}))
    return create_method(name)


@pytest.mark.parametrize("index", ["exact", "hnsw"])
def test_all_zero_queries_are_failures_counted_in_the_record_and_the_table(index, corridor, tmp_path):
    record = evaluate_method(oracle("blank-oracle", BLANK), corridor, ks=(1, 5), cache_dir=tmp_path, index=index)
    assert record["recall"] == {"1": 97.297297, "5": 97.297297}  # 108 of 111: was 100, queries 0-2 "finding" image 0
    assert record["counts"]["all_zero_queries"] == 3 and record["counts"]["all_zero_database"] == 1
    assert NOTE in " ".join(results_table(record).caption.split())
    arrays = per_query(record)
    assert arrays["first_positive_rank"][:4].tolist() == [0, 0, 0, 1]
    assert arrays["all_zero"].tolist() == [1, 1, 1] + [0] * 108
    assert (arrays["similarities"][:3] == 0).all()  # their inner products: no confident match
    if index == "exact":  # still listed, by the tie rule: what a re-ranking stage is handed
        assert arrays["database_indices"][0].tolist() == [0, 1, 2, 3, 4]
    # the top-1 PR curve counts them as wrong matches at similarity 0 (every other query is right at 1)
    assert record["recall_at_100_precision"] == 1.0 and record["auc_pr"] == 1.0

    save_result(record, tmp_path)
    [stored] = read_results(tmp_path)
    assert stored["counts"] == record["counts"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # stored metrics that disagree with the arrays would warn
        assert proven(stored)["recall"] == record["recall"]
    truth, problems = Truth("corridor:vpr-bench", 111, corridor.positives, for_dataset(corridor)), []
    rescore(stored, per_query(stored), truth, problems)  # a bundle's check re-scores the lists: it agrees
    assert problems == []
    rescore({**stored, "counts": {**stored["counts"], "all_zero_queries": 0}}, per_query(stored), truth, problems)
    assert problems == ["its counts say 0 all-zero queries; its arrays flag 3"]


def test_a_run_without_all_zero_rows_says_so_and_keeps_its_arrays(corridor, tmp_path):
    record = evaluate_method(oracle("oracle", ()), corridor, ks=(1,), cache_dir=tmp_path)
    assert record["recall"] == {"1": 100.0}
    assert record["counts"]["all_zero_queries"] == record["counts"]["all_zero_database"] == 0
    assert "all_zero" not in record["per_query"] and "all-zero" not in results_table(record).caption


def test_rows_read_more_than_once_are_counted_once(tiles_of_1024):
    """Queries in several chunks read the database once per chunk, and tied queries are searched again:
    each all-zero row is still counted once; one in a short, padded last tile is placed right."""
    from search_rows import budget_for, unit

    database, queries = unit(5000, 8, 1), unit(2248, 8, 2)  # the queries' last tile: 200 rows, padded to 256
    database[[5, 4999]] = 0
    queries[[0, 1100, 2247]] = 0
    queries[7] = database[9]
    database[10:40] = database[9]  # more tied rows than candidates: query 7 is searched again
    for budget in (10**9, budget_for(database, queries, 5, chunks=5, query_chunks=3)):
        found = exact_search(database, queries, 5, memory_budget=budget)
        assert np.flatnonzero(found.all_zero.queries).tolist() == [0, 1100, 2247] and found.all_zero.database == 2
        assert found.indices[0].tolist() == [0, 1, 2, 3, 4] and (found.scores[0] == 0).all()
        assert found.indices[7].tolist() == [9, 10, 11, 12, 13]
        assert found.info["queries_searched_again_for_ties"] == 1  # query 7: not the all-zero ones
    assert found.info["query_chunks"] > 1 and found.info["chunks"] > 1  # the database read more than once


def test_a_rerank_keeps_them_failures_also_from_frozen_candidates(shared_data, tmp_path):
    """A stage is handed the tie rule's candidates of an all-zero query (database images 0, 1, ...): it
    may re-order them, but the query still counts as a failure, and its stage's ceiling says so; a
    candidates file carries which queries were all zero."""
    oracle("blank-oracle", BLANK)
    settings = RunSettings(data_dir=shared_data, cache_dir=tmp_path / "cache")
    path = tmp_path / "candidates.h5"
    export_candidates(resolve_spec("blank-oracle", "corridor", data_dir=shared_data), settings, path, k=20)
    spec = resolve_spec("blank-oracle", "corridor", stages=[{"name": "aqe", "k": 20, "n": 2}], ks=(1, 5),
                        data_dir=shared_data)
    for run in (settings, dataclasses.replace(settings, candidates=path)):
        record = evaluate(spec, run)
        assert record["recall"] == {"1": 97.297297, "5": 97.297297} and record["stages"][0]["ceiling_recall"] == 97.297297
        assert record["counts"]["all_zero_queries"] == 3 and record["counts"]["all_zero_database"] == 1
    with h5py.File(path, "a") as f:  # edited by hand: a count beyond the database
        f.attrs["all_zero_database"] = 5000
    with pytest.raises(VPRBenchError, match=r"its all-zero rows \(all_zero, all_zero_database\) are not one flag"):
        evaluate(spec, dataclasses.replace(settings, candidates=path))


def test_a_sequence_stage_places_them_from_their_neighbours(shared_data, tmp_path):
    """On the sequence track an all-zero query is scored as it is matched (a blank frame in a sequence
    is placed by the frames around it); the record still counts it and flags no failure."""
    oracle("blank-oracle", BLANK)
    spec = resolve_spec("blank-oracle", "corridor", stages=["seqslam"], ks=(1, 5), data_dir=shared_data)
    record = evaluate(spec, RunSettings(data_dir=shared_data, cache_dir=tmp_path))
    assert record["track"] == "sequence" and record["counts"]["all_zero_queries"] == 3
    assert "all_zero" not in record["per_query"]
    first = per_query(record)["first_positive_rank"]
    assert (first[:3] > 0).all()  # the frames around them carry them to their place
    truth, problems = Truth("corridor:vpr-bench", 111, load_dataset("corridor", shared_data).positives,
                            for_dataset(load_dataset("corridor", shared_data))), []
    rescore(record, per_query(record), truth, problems)
    assert problems == []


class _Centred(Oracle):
    """The oracle whose rows are moved off the origin by a whole-matrix post-processing (as centring does)."""

    def postprocess(self, database, queries):
        shift = np.full(database.shape[1], 0.05, dtype=np.float32)
        return database + shift, queries + shift


@pytest.mark.parametrize("how", ["pca", "hook"])
def test_an_image_with_nothing_described_stays_so_after_post_processing(how, corridor, tmp_path):
    """Was: PCA-whitening's centring turned every all-zero row into one and the same nonzero vector,
    so such queries matched an image (and counted as hits when it was a positive) and were not counted."""
    from vprbench.aggregation import PCAWhitening

    extra = {"postprocessor": lambda self: PCAWhitening(dim=64)} if how == "pca" else {}
    register_method(f"blank-{how}", type(f"Blank{how}", (_Centred if how == "hook" else Oracle,),
                                         {"blank": frozenset(BLANK), **extra}))
    record = evaluate_method(create_method(f"blank-{how}"), corridor, ks=(1, 5), cache_dir=tmp_path)
    assert record["counts"]["all_zero_queries"] == 3 and record["counts"]["all_zero_database"] == 1
    assert per_query(record)["all_zero"].tolist()[:4] == [1, 1, 1, 0]
    assert record["recall"]["5"] <= 97.297297  # queries 0-2 fail at every K
