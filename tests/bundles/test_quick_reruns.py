"""What a new user meets after `evaluate --data-dir` on the real Corridor: a quick re-run asking fewer K,
`leaderboard` without --data-dir, and `compare` of cells no ground truth here checked."""
import json
import shutil
from pathlib import Path

import numpy as np

from vprbench.cli.main import main
from vprbench.evaluation import read_results


def _said(capsys) -> str:
    return " ".join(capsys.readouterr().out.split())


def test_a_rerun_asking_fewer_k_leaves_the_complete_runs_r10_and_r20(store, shared_data, tmp_path):
    """Was `| hog | … | 48.6 | 75.7 | – | – |`: the newest run reporting R@1 and R@5 filled the cell, though
    a complete run of the row has the very same top-K lists."""
    [complete] = [r for r in read_results(store) if r["label"] == "hog"]
    assert main(["evaluate", "--method", "hog", "--dataset", "corridor", "--k", "1", "5", "--cache-dir", str(store),
                 "--data-dir", str(shared_data)]) == 0
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs), "--cache-dir", str(store),
                 "--data-dir", str(shared_data)]) == 0
    page = (docs / "leaderboard" / "corridor.md").read_text()
    [row] = [line for line in page.splitlines() if line.startswith("| hog | none")]
    recall = complete["recall"]
    assert f"| {recall['10']:.1f} | {recall['20']:.1f} |" in row, row
    [run] = [line for line in page.splitlines() if line.startswith("| hog | measured here")]
    assert f"<code>{complete['run_id']}</code>" in run and "| 1 |" in run  # the whole run, the re-run passed over


def test_leaderboard_without_data_dir_re_scores_at_the_copy_the_run_read(store, tmp_path, capsys):
    """Was "2 of 2 cell(s) were NOT re-scored ... not in the data root" although the records name the copy
    they read. That copy proves them by its ground truth's content, never by its name."""
    assert main(["leaderboard", "show", "--cache-dir", str(store)]) == 0
    assert "Every cell was re-scored from its top-K indices against the ground truth on this machine." in _said(capsys)

    other = tmp_path / "other-corridor"  # a copy whose ground truth differs: named corridor, proves nothing
    shutil.copytree(Path(read_results(store)[0]["dataset_root"]), other)
    truth = np.load(other / "ground_truth_new.npy", allow_pickle=True)
    truth[0][1] = truth[0][1][:1]
    np.save(other / "ground_truth_new.npy", truth, allow_pickle=True)
    for path in (store / "results").rglob("*.json"):
        record = json.loads(path.read_text())
        if "dataset_root" in record:
            path.write_text(json.dumps({**record, "dataset_root": str(other)}))
    assert main(["leaderboard", "show", "--cache-dir", str(store)]) == 0
    out = _said(capsys)
    assert "2 of 2 cell(s) were NOT re-scored" in out and "another copy of corridor's ground truth" in out

    shutil.rmtree(other)  # no copy at all: the data root's reason, as before
    assert main(["leaderboard", "show", "--cache-dir", str(store)]) == 0
    assert "2 of 2 cell(s) were NOT re-scored" in (out := _said(capsys)) and "is not in the data root" in out


def test_compare_says_when_its_cells_were_not_re_scored(store, shared_data, tmp_path, capsys):
    """Was: intervals and p-values with no word of it, where `leaderboard` says so."""
    compare = ["leaderboard", "compare", "hog", "hog [resize=96x128]", "--dataset", "corridor",
               "--cache-dir", str(store)]
    assert main([*compare, "--data-dir", str(tmp_path / "no-data")]) == 0
    out = _said(capsys)
    assert "paired bootstrap p" in out
    assert "2 of 2 cell(s) were NOT re-scored against a ground truth" in out and "is not in the data root" in out
    assert main([*compare, "--data-dir", str(shared_data)]) == 0
    assert "re-scored" not in _said(capsys)  # proven cells: nothing to say
