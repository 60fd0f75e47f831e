"""A run fills a cell only when its top-K indices re-score to its numbers against the ground truth
on this machine (the code `results verify` uses): per-query ranks rewritten to a perfect score, with
the sha256 and summary numbers made to match (a careful forger), once published as 100.0 / 100.0.
Without the dataset here the page and terminal say the cells are not re-scored."""
import hashlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
from own_folders import corridor_folder

from vprbench.cli.main import main
from vprbench.evaluation import read_results
from vprbench.evaluation.metrics import kept_metrics, recall_at_k, top1_precision_recall


def _forge_perfect(record: dict) -> Path:
    """Every query with a positive found at rank 1: ranks, recall and PR metrics consistent, sha256 updated."""
    path = Path(record["_source"])
    stored = json.loads(path.read_text())
    npz = path.parent / stored["per_query"]["file"]
    arrays = dict(np.load(npz))
    first = np.where(arrays["positives"] > 0, 1, 0).astype(arrays["first_positive_rank"].dtype)
    arrays["first_positive_rank"] = first
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    npz.write_bytes(buffer.getvalue())
    ks = sorted(int(k) for k in stored["recall"])
    pr = top1_precision_recall(arrays["similarities"][:, 0].astype(np.float64), first == 1)
    stored.update(kept_metrics(recall_at_k(first, ks), pr))
    stored["per_query"]["sha256"] = hashlib.sha256(buffer.getvalue()).hexdigest()
    path.write_text(json.dumps(stored))
    return path


@pytest.fixture
def forged(store):
    return _forge_perfect(read_results(store)[0])


def test_publish_leaves_a_forged_run_out_naming_its_file(store, forged, shared_data, tmp_path, capsys):
    docs = tmp_path / "docs"
    with pytest.warns(UserWarning, match=rf"{forged}: its per-query top-K indices do not re-score to its numbers "
                                         r"against the ground truth of corridor .*query \d+: its first positive"):
        code = main(["leaderboard", "publish", "--to", str(docs), "--cache-dir", str(store), "--data-dir", str(shared_data)])
    err = capsys.readouterr().err
    assert code == 1 and "1 run(s) do not re-score to their numbers against the ground truth" in err
    assert "Traceback" not in err
    page = (docs / "leaderboard" / "corridor.md").read_text()
    assert "100.0" not in page  # the forged score fills no cell; the other, true run still does
    overview = (docs / "leaderboard" / "index.md").read_text()
    assert "Every cell was re-scored from its top-K indices against the ground truth on this machine." in overview


def test_show_refuses_it_too(store, forged, shared_data, capsys):
    with pytest.warns(UserWarning, match="do not re-score to its numbers"):
        code = main(["leaderboard", "show", "--cache-dir", str(store), "--data-dir", str(shared_data), "--format", "csv"])
    out, err = capsys.readouterr()
    assert code == 1 and "100.0" not in out


def test_without_the_ground_truth_the_cells_are_said_not_re_scored(store, tmp_path, capsys):
    code = main(["leaderboard", "show", "--cache-dir", str(store), "--data-dir", str(tmp_path / "no-data")])
    out = " ".join(capsys.readouterr().out.split())
    assert code == 0
    assert "2 of 2 cell(s) were NOT re-scored against a ground truth" in out and "corridor" in out


def test_a_forged_run_on_a_folder_of_ones_own_is_refused_and_a_moved_folder_said(shared_data, tmp_path, capsys):
    """Own data: the folder the record names is re-read (its protocol hash must still be the run's)."""
    own, cache = corridor_folder(shared_data, tmp_path / "campus", database=12, queries=8), tmp_path / "cache"
    assert main(["evaluate", "--method", "hog", "--resize", "32", "32", "--k", "1", "5", "10", "--dataset", str(own), "--cache-dir", str(cache)]) == 0
    assert main(["leaderboard", "show", "--cache-dir", str(cache)]) == 0
    assert "Every cell was re-scored" in " ".join(capsys.readouterr().out.split())
    forged = _forge_perfect(read_results(cache)[0])
    with pytest.warns(UserWarning, match=rf"{forged}: its per-query top-K indices do not re-score"):
        assert main(["leaderboard", "show", "--cache-dir", str(cache)]) == 1
    capsys.readouterr()
    own.rename(tmp_path / "moved")
    assert main(["leaderboard", "show", "--cache-dir", str(cache)]) == 0  # not provable here: shown, and said
    out = " ".join(capsys.readouterr().out.split())
    assert "1 of 1 cell(s) were NOT re-scored against a ground truth" in out and "does not exist" in out
    # was: "(Dataset folder ... does not exist (closest existing folder)." (cut inside its parenthesis), and only
    # "A benchmark's copy under --data-dir proves its cells", which cannot prove a folder of one's own
    assert f"its ground truth is not here (Dataset folder {own} does not exist)." in out
    assert "a folder of your own, back unchanged at the path its runs name, proves theirs." in out


def test_the_dataset_page_says_so_too(store, tmp_path, capsys):
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs), "--cache-dir", str(store), "--data-dir", str(tmp_path / "no-data")]) == 0
    for page in ("index.md", "corridor.md"):
        text = " ".join((docs / "leaderboard" / page).read_text().split())
        assert "2 of 2 cell(s) were NOT re-scored against a ground truth" in text, page
        assert str(tmp_path) not in text  # the data root's path cut to its name, as every page does


def test_the_python_api_re_scores_as_the_command_line_does(records, shared_data, tmp_path):
    """Before: leaderboard(records) and build_board(records) re-scored nothing and truth_note said
    nothing, where `vprbench leaderboard` re-scores every cell and says which it could not."""
    from vprbench.leaderboard import build_board, leaderboard
    from vprbench.leaderboard.truth import truth_note

    note = truth_note(build_board(records))  # no ground truth given: said, not silent
    assert "2 of 2 cell(s) were NOT re-scored" in note and "built without a ground truth" in note
    table = leaderboard(records, shared_data)
    assert table.attrs["truth_note"].startswith("Every cell was re-scored"), table.attrs
    with pytest.warns(UserWarning, match="2 of 2 cell.s. were NOT re-scored"):
        leaderboard(records, tmp_path / "no-data")
