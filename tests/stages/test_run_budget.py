"""A run's memory budget is checked once, for retrieval and every stage together, before any search:
a budget that retrieval's search fits but a stage does not is refused at once, naming the stage and
the budget the whole run needs (not retrieval's need first, then the stage's after the search ran)."""
from __future__ import annotations

import re

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.errors import VPRBenchError
from vprbench.evaluation.budget import stage_needs
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
                                                r"not a number of bytes"):
            stage_needs([Says(wrong)], rows, rows, 2)
