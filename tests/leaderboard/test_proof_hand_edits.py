"""Hand edits of a record's JSON that the arrays contradict: max F1 (downloads, the sequence track)
and the depth of its per-query arrays (R@10 / R@20 read from ranks that stop at 5) are shown as
the arrays say, and named in the warning."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vprbench.evaluation import read_results, save_result
from vprbench.evaluation.metrics import top1_precision_recall
from vprbench.leaderboard import build_board
from vprbench.leaderboard.downloads import summary
from vprbench.leaderboard.tables import cell_stats


def _edit(path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_a_hand_edited_max_f1_is_named_and_shown_recomputed(make_record):
    path = save_result(make_record(quality=0.4, seed=3))
    _edit(path, lambda d: d.update(max_f1=0.999))
    with pytest.warns(UserWarning, match=r"max_f1 0\.999 \(arrays: "):
        [cell] = build_board(read_results()).cells.values()
    arrays = cell.arrays
    truth = top1_precision_recall(arrays["similarities"][:, 0].astype(np.float64), arrays["first_positive_rank"] == 1)
    assert truth["max_f1"] < 0.99
    assert cell.record["max_f1"] == pytest.approx(truth["max_f1"], abs=1e-6)
    assert summary(cell, cell_stats(cell))["max_f1"] == pytest.approx(truth["max_f1"], abs=1e-6)


def test_a_per_query_depth_edited_deeper_fills_no_deeper_recall(make_record):
    """A K 1 5 run keeps its top 5: its JSON saying k = 20 must not turn R@5 into an 'R@10' and 'R@20'."""
    path = save_result(make_record(k=5, ks=(1, 5), quality=0.4, seed=4))
    _edit(path, lambda d: d["per_query"].update(k=20))
    with pytest.warns(UserWarning, match=r"per_query\.k 20 \(arrays: 5\)"):
        [cell] = build_board(read_results()).cells.values()
    assert cell.arrays["database_indices"].shape[1] == 5
    assert cell.recall(5) is not None and cell.recall(10) is None and cell.recall(20) is None
    assert cell_stats(cell, ks=(10,))[10] == {"value": None, "ci": None}
    shown = summary(cell, cell_stats(cell))
    assert shown["r10"] is None and shown["r20"] is None
