"""A run's memory budget is checked once, for retrieval and every stage together, before any search:
a budget that retrieval's search fits but a stage does not is refused at once, naming the stage and
the budget the whole run needs (not retrieval's need first, then the stage's after the search ran)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from vprbench import Method, register_method
from vprbench.aggregation.pca import PCAWhitening
from vprbench.cli.main import main
from vprbench.errors import VPRBenchError
from vprbench.evaluation.budget import check_run_budget, retrieval_need, stage_needs
from vprbench.evaluation.postprocess import RowShape, TransformedRows, check_joint_budget, planned
from vprbench.evaluation.retrieve import retrieve
from vprbench.row_sources import ArrayRows, parse_memory
from vprbench.stages.base import Stage


def spied(monkeypatch) -> list[str]:
    """The searches and stage runs of a run, by name, as they start."""
    import vprbench.evaluation.pipeline as pipeline
    import vprbench.evaluation.retrieve as retrieve
    import vprbench.stages.sequence.search as sequence

    calls = []
    for module, name in ((retrieve, "exact_search"), (sequence, "sequence_search"), (pipeline, "run_stages")):
        real = getattr(module, name)

        def spy(*args, _real=real, _name=name, **kwargs):
            calls.append(_name)
            return _real(*args, **kwargs)

        monkeypatch.setattr(module, name, spy)
    return calls


# measured on Corridor: sad's search 2.1 MB, SeqSLAM 2.3 MB; hog's search 48 MB, dba re-ranking all 111 images 50 MB
# (what dba needs before the search is known is one query's k images: here all of them)
@pytest.mark.parametrize("method, stage, budget, part", [
    ("sad", ["--sequence", "seqslam"], "2.2MB", "stage 'seqslam'"),
    ("hog", ["--rerank", "dba", "--rerank-k", "111"], "49MB", "stage 'dba'"),
])
def test_one_refusal_names_the_budget_the_whole_run_needs(method, stage, budget, part, shared_data, stage_cache,
                                                          capsys, monkeypatch):
    calls = spied(monkeypatch)
    run = ["evaluate", "--method", method, "--dataset", "corridor", *stage, "--data-dir", str(shared_data),
           "--cache-dir", str(stage_cache), "--k", "1", "5"]
    code = main([*run, "--search-memory", budget])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "Traceback" not in err and len(err.splitlines()) == 1, err
    assert f"too small for this run: {part} needs the most" in err, err
    assert not calls, calls  # refused before retrieval's search and before any stage
    searched = parse_memory(re.search(r"retrieval's exact search ([\d.]+ \w+)", err).group(1))
    need = parse_memory(re.search(r"to at least ([\d.]+ \w+)\.$", err).group(1))
    assert searched <= parse_memory(budget) < need  # retrieval alone fits it: only the plan sees the stage's need
    code = main([*run, "--search-memory", str(need)])
    err = capsys.readouterr().err
    assert code == 0 and "too small" not in err, err  # the number named runs the whole run: no second refusal
    assert "run_stages" in calls


class Says(Stage):
    def __init__(self, need):
        super().__init__()
        self.name, self.need = "says", need

    def least_budget(self, database, queries, k):
        return self.need


def test_a_stage_least_budget_that_is_not_bytes_is_refused_naming_the_stage():
    rows = ArrayRows(np.zeros((4, 8), dtype=np.float32))
    assert stage_needs([Says(None), Says(np.int64(5))], rows, rows, 2) == [("stage 'says'", 5)]
    for wrong in ("lots", 1.5, -1, True):
        with pytest.raises(VPRBenchError, match=rf"Stage 'says': least_budget\(\) returned {re.escape(repr(wrong))}, "
                                                r"not a whole number >= 0 or None; fix the stage\.$"):
            stage_needs([Says(wrong)], rows, rows, 2)


# ------------------------------------------------------------ with a post-processor fitted first
class Whitened(Method):
    """Each Corridor image as a fixed random row of its frame (a query as its database image), PCA-whitened
    to `pca_dim`: a fit before the search, with nothing to run but a random generator."""

    def __init__(self, dim: int = 2048, pca_dim: int = 32, device: str = "cpu"):
        self.dim, self.pca_dim = dim, pca_dim

    def provenance(self) -> dict:
        return {"weights": {"source": "none"}}

    def describe(self, images):
        rows = np.stack([np.random.default_rng(int(Path(p).stem)).standard_normal(self.dim) for p in images])
        return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)

    def postprocessor(self):
        return PCAWhitening(self.pca_dim)


@pytest.fixture
def whitened(scratch_methods):
    register_method("whitened", Whitened)


def test_a_fit_below_the_budget_is_planned_with_the_search_and_the_stages(whitened, shared_data, tmp_path, capsys,
                                                                          monkeypatch):
    calls = spied(monkeypatch)
    run = ["evaluate", "--method", "whitened", "--dataset", "corridor", "--rerank", "dba", "--rerank-k", "111",
           "--data-dir", str(shared_data), "--cache-dir", str(tmp_path / "cache"), "--k", "1", "5"]
    fits = PCAWhitening(32).exact_memory(RowShape({"count": 111, "dim": 2048, "dtype": "float32"}))
    assert parse_memory("500kB") < fits  # below the fit's need too: it refused first, and the search's after it
    code = main([*run, "--search-memory", "500kB"])
    err = capsys.readouterr().err.strip()
    assert code != 0 and "Traceback" not in err and len(err.splitlines()) == 1, err
    needs = {part: parse_memory(need) for part, need in re.findall(r"(the PCAWhitening fit|retrieval's exact search|"
                                                                   r"stage 'dba') ([\d.]+ \w+)", err)}
    assert set(needs) == {"the PCAWhitening fit", "retrieval's exact search", "stage 'dba'"}, err
    most = max(needs, key=needs.get)
    assert f"too small for this run: {most} needs the most" in err and not calls, err
    need = parse_memory(re.search(r"to at least ([\d.]+ \w+)\.$", err).group(1))
    code = main([*run, "--search-memory", str(need), "--json"])
    captured = capsys.readouterr()
    assert code == 0 and "too small" not in captured.err, captured.err  # no second refusal, after the fit
    assert json.loads(captured.out)["search"]["postprocess"]["state"] == "fitted" and "run_stages" in calls


class Shape(RowShape):
    """Rows by shape only: a refused plan reads none."""

    def read_rows_at(self, indices):
        raise AssertionError("a row was read")


class Fitted(Exception):
    pass


def test_a_fit_that_needs_the_most_is_named_and_its_need_runs_it(monkeypatch):
    # AnyLoc-VLAD's shape on Pitts-30k's database to 512 dims: the fit needs more than the search of its output
    database, queries = (Shape({"count": n, "dim": 49152, "dtype": "float32"}) for n in (10000, 1000))
    method = Whitened(pca_dim=512)

    def plan(rows, asked, fit=()):
        check_run_budget([*fit, ("retrieval's exact search", retrieval_need("cosine", rows, asked, 10))], budget)
    budget = parse_memory("100MB")
    with pytest.raises(VPRBenchError, match="too small for this run: the PCAWhitening fit needs the most") as refused:
        retrieve(method, database, queries, 10, memory_budget=budget, check=plan)
    need = parse_memory(re.search(r"to at least ([\d.]+ \w+)\.$", str(refused.value)).group(1))
    assert need >= PCAWhitening(512).least_budget(database, budget)

    def fit(self, rows, memory_budget):
        self.check_budget(rows, memory_budget)  # the fit's own check: no second refusal
        raise Fitted
    monkeypatch.setattr(PCAWhitening, "fit", fit)
    budget = need
    with pytest.raises(Fitted):
        retrieve(method, database, queries, 10, memory_budget=budget, check=plan)


def test_the_plan_reads_the_post_processed_rows_cost_and_the_stacked_fit_before_fitting():
    db = np.random.default_rng(0).standard_normal((300, 64)).astype(np.float32)
    rows, pca = ArrayRows(db), PCAWhitening(16)
    shaped, _, parts = planned(pca, rows, rows, rows, 2**30)
    assert shaped.read_cost() == TransformedRows(rows, pca.fit(db), counts_state=True).read_cost()
    assert parts == [("the PCAWhitening fit", pca.exact_memory(rows))]
    # a joint fit: planned on the databases stacked (their shape), not on the evaluated one
    seen = []
    check_joint_budget(Whitened(64, 16), 606, {"database": rows, "queries": rows}, 2**30, lambda *found: seen.append(found))
    assert seen[0][2] == [("the PCAWhitening fit", pca.exact_memory(RowShape({"count": 606, "dim": 64,
                                                                               "dtype": "float32"})))]


class Says16:
    def output_dim(self, rows):
        return "sixteen"


def test_a_post_processor_output_dim_that_is_no_number_is_refused_naming_it():
    rows = ArrayRows(np.zeros((4, 8), dtype=np.float32))
    with pytest.raises(VPRBenchError, match=r"Post-processor Says16: output_dim\(\) returned 'sixteen', not a whole "
                                            r"number >= 1; fix the post-processor\."):
        planned(Says16(), rows, rows, rows, 2**20)
