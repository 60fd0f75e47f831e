"""Every number shown comes from the run's per-query arrays; speeds from runs that measured them;
a method that declares its provenance later replaces its undeclared row."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results, save_result
from vprbench.evaluation.metrics import recall_at_k
from vprbench.evaluation.proof import proven
from vprbench.evaluation.results import read_record
from vprbench.leaderboard import build_board, grid
from vprbench.leaderboard import cells as cells_module


def edited(record: dict, r1: float) -> tuple[dict, str]:
    """Store `record`, then hand-edit R@1 in its JSON (as an attacker or a careless user would)."""
    path = save_result(record)
    data = json.loads(path.read_text())
    data["recall"]["1"] = r1
    path.write_text(json.dumps(data))
    return data, str(path)


def test_a_hand_edited_recall_is_named_and_shown_recomputed(make_record, monkeypatch, capsys):
    record = make_record(quality=0.4, seed=1)
    true_r1 = record["recall"]["1"]
    _, path = edited(record, 99.0)
    [stored] = read_results()
    assert stored["recall"]["1"] == 99.0  # the record really says 99

    with monkeypatch.context() as unchecked:  # the attack is real: without the check, 99.0 would be shown
        unchecked.setattr(cells_module, "proven", lambda r: r)
        assert grid(build_board(read_results())).loc["hog", "corridor"].startswith("99.0 /")

    with pytest.warns(UserWarning, match="disagree with its per-query arrays") as caught:
        board = build_board(read_results())
    assert path in str(caught[0].message) and "R@1 99 (arrays: " in str(caught[0].message)
    [cell] = board.cells.values()
    first = cell.arrays["first_positive_rank"]
    assert cell.recall(1) == pytest.approx(recall_at_k(first, [1])[1]) == pytest.approx(true_r1, abs=1e-4)
    assert grid(board).loc["hog", "corridor"].startswith(f"{true_r1:.1f} /")

    with pytest.warns(UserWarning, match=re.escape(path)):  # the command names the file ...
        assert main(["leaderboard", "--format", "csv"]) == 0
    out = capsys.readouterr().out
    assert f"{true_r1:.1f} /" in out and "99.0" not in out  # ... and shows the recomputed value


def test_compare_and_reproduce_read_the_recomputed_values(make_record, capsys):
    from vprbench.sweep.reproduce import measured

    a, b = make_record(quality=0.6, seed=1), make_record("netvlad", quality=0.3, seed=2)
    save_result(b)
    _, path = edited(a, 100.0)
    with pytest.warns(UserWarning, match="disagree"):
        assert main(["leaderboard", "compare", "hog", "netvlad", "--dataset", "corridor"]) == 0
    out = capsys.readouterr().out
    assert f"R@1 {a['recall']['1']:5.1f} %" in out and "100.0 %" not in out
    with pytest.warns(UserWarning, match="disagree"):
        value, _, _ = measured([read_record(path)], "r1")
    assert value == pytest.approx(a["recall"]["1"], abs=1e-4)


def test_a_sweep_shows_a_complete_cell_recomputed_and_reruns_one_without_arrays(make_record):
    """`vprbench run` and `reproduce` find a cell's record with find_result: it shows the values
    recomputed from the arrays (the stored 100.0 was shown as it was), and a record whose arrays are
    gone counts as no result, so the cell is evaluated again rather than shown from its JSON."""
    from vprbench.evaluation import find_result
    from vprbench.spec import RunSpec

    record = make_record(quality=0.6, seed=1)
    _, path = edited(record, 100.0)
    spec = RunSpec.model_validate(record["spec"])
    assert json.loads(open(path).read())["recall"]["1"] == 100.0  # the attack is real: the record says 100
    with pytest.warns(UserWarning, match="disagree"):
        found = find_result(spec)
    assert found["recall"]["1"] == pytest.approx(record["recall"]["1"], abs=1e-4) != 100.0
    Path(path).with_suffix(".npz").unlink()
    with pytest.warns(UserWarning) as caught:
        assert find_result(spec) is None
    assert any(f"{path} does not count as a result: its per-query arrays are missing" in str(w.message) for w in caught)


def test_arrays_that_do_not_fit_leave_the_run_out_with_the_reason(make_record):
    broken = make_record(seed=1)
    broken["per_query"]["first_positive_rank"] = [25] * len(broken["per_query"]["first_positive_rank"])  # beyond top 20
    short = make_record(seed=2)
    short["per_query"]["positives"] = short["per_query"]["positives"][:-1]
    with pytest.warns(UserWarning):
        for record in (broken, short):
            why = proven(record)
            assert isinstance(why, str) and "per-query arrays" in why
    none = make_record(seed=3)
    none.pop("per_query")
    assert "keeps no per-query arrays" in proven(none)


def test_a_run_served_from_stores_never_replaces_the_measured_speed(make_record, tmp_path):
    from vprbench.leaderboard import publish

    measured_run = make_record(seed=1, created="2026-01-01T00:00:00+00:00")
    measured_run["images_per_second"] = 211.0
    measured_run["hardware"] = {"cpu": "Test CPU 9000", "cpu_count": 2, "cuda": None}
    served = make_record(seed=1, created="2026-02-01T00:00:00+00:00")
    served.update(served_from_store=True, images_per_second=None, descriptors_computed={"database": 0, "queries": 0})
    for record in (measured_run, served):
        save_result(record)
    board = build_board(read_results())
    [cell] = board.cells.values()
    assert cell.record["run_id"] == served["run_id"]  # the newest run fills the cell ...
    assert cell.images_per_second == 211.0 and cell.timed["run_id"] == measured_run["run_id"]  # ... its speed does not
    assert cell.hardware == "Test CPU 9000 (2 cores), no GPU"

    out = publish(tmp_path / "docs")
    page = (out / "corridor.md").read_text()
    assert f"<code>{measured_run['run_id']}</code> on Test CPU 9000 (2 cores), no GPU" in page
    [row] = [line for line in page.splitlines() if line.startswith("| hog | none")]
    assert row.rstrip(" |").endswith("211.0")
    [entry] = json.loads((out / "downloads" / "leaderboard.json").read_text())
    assert (entry["images_per_second"], entry["speed_run_id"]) == (211.0, measured_run["run_id"])

    only_served = build_board([r for r in read_results() if r["run_id"] == served["run_id"]])
    assert next(iter(only_served.cells.values())).images_per_second is None  # nothing measured: no speed shown


def test_a_method_that_declares_provenance_later_replaces_its_undeclared_row(make_record, tmp_path):
    from vprbench.leaderboard import publish

    before = make_record("my-plugin", weights={"source": "undeclared"}, seed=1, created="2026-01-01T00:00:00+00:00")
    after = make_record("my-plugin", weights={"source": "none"}, seed=1, created="2026-02-01T00:00:00+00:00")
    assert before["row_key"] == after["row_key"]
    save_result(before)
    assert [r.name for r in build_board(read_results()).rows] == ["my-plugin † weights undeclared"]
    save_result(after)
    board = build_board(read_results())
    assert [r.name for r in board.rows] == ["my-plugin"]
    [(left_out, why)] = board.excluded
    assert left_out["run_id"] == before["run_id"] and "declares them (provenance())" in why
    page = (publish(tmp_path / "docs") / "corridor.md").read_text()
    assert "Paired tests" not in page  # never a method against itself


def test_recomputing_is_cached_by_the_arrays_sha256(make_record, monkeypatch):
    from vprbench.evaluation import proof

    path = save_result(make_record(seed=5))
    calls = []
    real = proof._recompute
    monkeypatch.setattr(proof, "_recompute", lambda *a: calls.append(1) or real(*a))
    proof._CACHE.clear()
    for _ in range(3):
        build_board(read_results())
    assert len(calls) == 1
    sha = json.loads(path.read_text())["per_query"]["sha256"]
    assert any(key[0] == sha for key in proof._CACHE)
    assert np.isfinite(next(iter(proof._CACHE.values()))["auc_pr"])


def test_a_speed_measured_under_one_protocol_serves_the_same_images_under_another(make_record):
    """Own data judged with +-1 and +-10 frames: the second run describes nothing (the store
    holds the images' descriptors), and its cell shows the first run's speed, naming that run."""
    measured_run = make_record(kind="own", unit="frames", radius=1, n_database=60, n_queries=50, seed=1,
                               created="2026-01-01T00:00:00+00:00")
    measured_run["images_per_second"] = 211.0
    served = make_record(kind="own", unit="frames", radius=10, n_database=60, n_queries=50, seed=1,
                         created="2026-02-01T00:00:00+00:00")
    served.update(served_from_store=True, images_per_second=None, descriptors_computed={"database": 0, "queries": 0})
    assert measured_run["dataset_fingerprints"]["images"] == served["dataset_fingerprints"]["images"]
    other_images = make_record(kind="own", unit="frames", radius=1, n_database=60, n_queries=50, seed=1,
                               created="2026-03-01T00:00:00+00:00")
    other_images["images_per_second"] = 99.0  # another copy whose images differ in content
    other_images["dataset_fingerprints"]["images"] = {"database": "0" * 64, "queries": "1" * 64}
    for record in (measured_run, served):
        save_result(record)
    board = build_board(read_results())
    speeds = {cell.column.detail: (cell.images_per_second, cell.timed["run_id"]) for cell in board.cells.values()}
    assert speeds == {"own, ±1 frame": (211.0, measured_run["run_id"]), "own, ±10 frames": (211.0, measured_run["run_id"])}
    alone = build_board([served, other_images])  # a speed measured on other images is not this cell's
    assert {cell.column.detail: cell.images_per_second for cell in alone.cells.values()} == \
        {"own, ±1 frame": 99.0, "own, ±10 frames": None}


def test_pr_metrics_come_from_the_similarities_the_record_keeps(make_record):
    """A record keeps similarities to 6 decimals, which merges near-ties; its PR metrics are computed
    from those kept values, so whoever recomputes them from the record (the leaderboard, `results
    verify`) finds the same. Here the second and third most confident top-1 matches tie once rounded
    (one right, one wrong): from the unrounded scores R@100%P was 2/48, from the record's arrays 1/48."""
    from vprbench.evaluation.metrics import top1_precision_recall
    from vprbench.evaluation.results import per_query

    record = make_record("method-02", "mid-atlantic-ridge", quality=0.4, seed=2)
    arrays = per_query(record)
    top1, correct = arrays["similarities"][:, 0], arrays["first_positive_rank"] == 1
    order = np.argsort(-top1, kind="stable")
    assert correct[order[0]] and top1[order[1]] == top1[order[2]] and correct[order[1]] != correct[order[2]]
    again = top1_precision_recall(top1, correct)
    assert record["recall_at_100_precision"] == round(again["recall_at_100_precision"], 8) == 0.02083333
    assert record["auc_pr"] == round(again["auc_pr"], 8) and record["max_f1"] == round(again["max_f1"], 8)
    assert not proven(record)["_proof"]["disagreed"]


def test_a_domain_mean_needs_every_dataset_measured(make_record):
    """reproduce's domain columns average datasets: one dataset without a run is no mean at all."""
    from vprbench.sweep.reproduce import measured

    a, b = make_record(quality=0.6, seed=1), make_record("netvlad", quality=0.3, seed=2)
    records = [read_record(save_result(r)) for r in (a, b)]
    value, low, high = measured(records, "r1")
    assert value == pytest.approx((a["recall"]["1"] + b["recall"]["1"]) / 2, abs=1e-4)
    assert low < value < high
    assert measured([records[0], None], "r1") is None and measured([None, records[1]], "r5") is None
