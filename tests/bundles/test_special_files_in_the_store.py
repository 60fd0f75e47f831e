"""A record, its per-query arrays or its row's card in the results store replaced by a named pipe or a
link to /dev/zero: `leaderboard show` (every listing of the store) hung on the pipe, or read /dev/zero until
'Out of memory'; `results export` hung. Each is now named in one line and left out, never read."""
import pytest
from special_files import no_hang, pipe_at

from vprbench.bundles import export_bundle
from vprbench.errors import VPRBenchError
from vprbench.evaluation import read_results
from vprbench.evaluation.results import per_query
from vprbench.paths import special_file


def test_a_link_to_a_device_counts_as_one(tmp_path):
    # not read here: before, a record linked to /dev/zero was read until the memory ran out
    assert special_file(pipe_at(tmp_path / "evil.json", "zero")) and special_file(pipe_at(tmp_path / "p.json"))
    assert not special_file(tmp_path) and not special_file(tmp_path / "absent.json")


def test_a_record_that_is_a_pipe_is_named_and_skipped(store, records, cli):
    folder = store / "results" / records[0]["protocol"]["hash"] / records[0]["row_key"]
    evil = pipe_at(folder / "evil.json")
    skipped = []
    with no_hang(), pytest.warns(UserWarning, match=rf"{evil} is not a readable JSON record \(it is a named pipe, "
                                                     r"device or socket\)\. Skipped \(nothing was deleted\)\."):
        found = read_results(store, skipped=skipped)
    assert skipped == [evil] and sorted(r["run_id"] for r in found) == sorted(r["run_id"] for r in records)
    with no_hang(), pytest.warns(UserWarning, match="is not a readable JSON record"):
        code, out, err = cli("leaderboard", "show", "--cache-dir", store)
    assert code == 1 and "Traceback" not in err and "1 stored file(s) could not be read" in err, out + err


def test_per_query_arrays_that_are_a_pipe_are_named_and_left_out(store, records, tmp_path):
    record = records[0]
    arrays = pipe_at(store / "results" / record["protocol"]["hash"] / record["row_key"] / record["per_query"]["file"])
    with no_hang(), pytest.warns(UserWarning, match=rf"Per-query data {arrays} of run {record['run_id']} is unreadable "
                                                     r"\(it is a named pipe, device or socket, not a file\)"):
        assert per_query(record) is None
    with no_hang(), pytest.raises(VPRBenchError, match=rf"^Run {record['run_id']}: {arrays} is a named pipe, device or "
                                                        r"socket, not a file: remove it .* Nothing was exported\.$"):
        export_bundle(records, tmp_path / "runs.tar.gz")
    assert not (tmp_path / "runs.tar.gz").exists()


def test_a_card_that_is_a_pipe_is_refused_at_export(store, records, tmp_path):
    card = pipe_at(store / "results" / "methods" / f"{records[0]['row_key']}.json")
    with no_hang(), pytest.raises(VPRBenchError, match=rf"{card} is a named pipe, device or socket, not a file: remove "
                                                        r"it \(a card is rebuilt"):
        export_bundle(records, tmp_path / "runs.tar.gz")
