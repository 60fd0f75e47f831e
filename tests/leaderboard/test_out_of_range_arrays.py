"""A record whose per-query arrays do not fit it (a database index past the database, a negative
one, shapes of another run) is never used: it is left out of every cell with a warning naming
the run (its metrics cannot be recomputed), and publish still writes every page (it once ended in an IndexError traceback from
the mosaic, and a negative index showed the wrong image without a word)."""
import io
import json
import hashlib

import numpy as np
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import per_query, read_results, save_result
from vprbench.evaluation import results


def _edit_arrays(path, change):
    """Rewrite a stored run's .npz with `change` applied, and its sha256 in the record (a careful forger)."""
    record = json.loads(path.read_text())
    npz = path.with_suffix(".npz")
    arrays = dict(np.load(npz))
    change(arrays)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    npz.write_bytes(buffer.getvalue())
    record["per_query"]["sha256"] = hashlib.sha256(buffer.getvalue()).hexdigest()
    path.write_text(json.dumps(record))


def _past_the_end(arrays):
    arrays["database_indices"][:, 0] = 111
    arrays["database_indices"][1, 1] = -3


@pytest.fixture
def forged(make_record, shared_data):
    """A Corridor run on the real images whose top-1 indices all lie past the 111 database images."""
    record = make_record("hog", root=shared_data / "corridor", quality=0.6, seed=1)
    path = save_result(record)
    _edit_arrays(path, _past_the_end)
    return path


def test_the_attack_is_real(forged, tmp_path, shared_data, monkeypatch, capsys):
    """Without the range check, and with the run's images on disk (the content check passed), the
    mosaic indexes past Corridor's database list (the re-score against the ground truth, which would
    also refuse it, left out too)."""
    from vprbench.datasets import load_dataset
    from vprbench.leaderboard import figures, truth

    monkeypatch.setattr(results, "_in_range", lambda record, arrays: arrays)
    monkeypatch.setattr(truth, "against_truth", lambda record, truth: ("unproven", "not re-scored in this test"))
    corridor = load_dataset("corridor", shared_data, fetch=False)
    monkeypatch.setattr(figures, "_dataset_of", lambda *args, **kwargs: corridor)
    with pytest.raises(IndexError):
        main(["leaderboard", "publish", "--to", str(tmp_path / "docs"), "--data-dir", str(shared_data)])


def test_publish_leaves_the_run_out_and_names_it(forged, tmp_path, shared_data, capsys):
    docs = tmp_path / "docs"
    [record] = read_results()
    with pytest.warns(UserWarning, match=rf"run {record['run_id']} .*query 0 lists a database index outside the "
                                         "record's 111 database images"):
        assert main(["leaderboard", "publish", "--to", str(docs), "--data-dir", str(shared_data)]) == 0
    assert not (docs / "leaderboard" / "corridor.md").exists()  # no cell: its metrics cannot be proven
    left_out = (docs / "leaderboard" / "index.md").read_text().split("## Runs left out")[1].split("\n## ")[0]
    assert f"<code>{record['run_id']}</code> | hog | corridor | its per-query arrays are missing or damaged" in left_out
    assert "outside the record&#x27;s 111 database images" in left_out
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("change, reason", [
    (lambda a: a.update(database_indices=a["database_indices"][:-1]), "not those of the record's 111 queries"),
    (lambda a: a["database_indices"].__setitem__((5, 0), -1), "query 5 lists a database index outside"),
    (lambda a: a["first_positive_rank"].__setitem__(0, 99), "a first-positive rank lies outside 0..20"),
])
def test_arrays_that_do_not_fit_the_record_are_not_used(make_record, change, reason):
    path = save_result(make_record("hog", seed=2))
    [record] = read_results()
    assert per_query(record) is not None  # sound before the edit
    _edit_arrays(path, change)
    [record] = read_results()
    with pytest.warns(UserWarning, match=reason):
        assert per_query(record) is None
