"""`results export` read a run's per-query arrays and its row's method card by their names in the store:
another run's arrays copied over a run's, or another row's card copied over a row's, went into the
bundle as they were, and every verifier refused it (sha256 mismatch; a card that disagrees with its
record). Export now checks both as verifiers do: arrays that are not the record's are refused in one
line naming the file, a card that does not describe the record is rebuilt from it (said)."""
import shutil

import pytest
from bundle_files import read_bundle

from vprbench.evaluation.results import card_bytes


def arrays_of(store, record):
    return store / "results" / record["protocol"]["hash"] / record["row_key"] / record["per_query"]["file"]


def test_arrays_copied_over_a_runs_own_are_refused_naming_the_file(store, records, tmp_path, cli):
    ours, theirs = records
    shutil.copyfile(arrays_of(store, theirs), arrays_of(store, ours))
    to = tmp_path / "runs.tar.gz"
    code, out, err = cli("results", "export", "--method", "hog", "--dataset", "corridor", "--to", to, "--cache-dir", store)
    assert code == 1 and not to.exists() and "Traceback" not in err, out + err
    assert f"error: Run {ours['run_id']}: its per-query arrays {arrays_of(store, ours)} do not match the sha256 its " \
           f"record gives (replaced, edited or damaged): delete it and its record {ours['run_id']}.json" in " ".join(err.split())
    # the other run exports alone, and verifies
    code, out, err = cli("results", "export", "--run", theirs["run_id"], "--to", to, "--cache-dir", store)
    assert code == 0, out + err


def test_a_card_copied_from_another_row_is_rebuilt_from_the_record(store, records, shared_data, tmp_path, cli):
    ours, theirs = records
    card = store / "results" / "methods" / f"{ours['row_key']}.json"
    shutil.copyfile(store / "results" / "methods" / f"{theirs['row_key']}.json", card)
    to = tmp_path / "runs.tar.gz"
    with pytest.warns(UserWarning, match=rf"Method card \S+{ours['row_key']}\.json does not describe run "
                                         rf"{ours['run_id']} \(disagrees with the record on row_key, label, options, given: "
                                         r"copied or edited\); the bundle holds the card rebuilt from the record\."):
        code, out, err = cli("results", "export", "--run", ours["run_id"], "--to", to, "--cache-dir", store)
    assert code == 0, out + err
    stored = {k: v for k, v in ours.items() if not k.startswith("_")}
    assert read_bundle(to)[f"methods/{ours['row_key']}.json"] == card_bytes(stored)
    code, out, err = cli("results", "verify", to, "--data-dir", shared_data)
    assert code == 0 and out.count(": ok, re-scored from its arrays") == 1, out + err
