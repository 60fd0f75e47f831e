"""`vprbench evaluate --json` prints the record as stored: its metrics, and its per-query arrays by
reference to the .npz saved beside it (they once came inline: queries x K numbers, one a line, and a
per_query section unlike the stored one). `--inline-arrays` asks for them inline."""
import json

import numpy as np

from vprbench.evaluation import per_query, read_results

EVALUATE = ("evaluate", "--method", "hog", "--resize", 16, 16, "--k", 1, 5, "--dataset", "corridor", "--quiet")


def test_json_is_the_stored_record(cli, shared_data):
    code, out, err = cli(*EVALUATE, "--data-dir", shared_data, "--json")
    assert code == 0, err
    printed = json.loads(out)
    [stored] = read_results()
    assert printed == {k: v for k, v in stored.items() if k != "_source"}
    assert set(printed["recall"]) == {"1", "5"} and 0 <= printed["recall"]["1"] <= printed["recall"]["5"] <= 100
    assert printed["per_query"]["file"] == f"{printed['run_id']}.npz" and printed["per_query"]["queries"] == 111
    assert not {"database_indices", "similarities", "first_positive_rank", "positives"} & set(printed["per_query"])
    assert len(out.splitlines()) < 1500  # 111 queries x K=5 inline took over 2,700 lines

    code, out, err = cli(*EVALUATE, "--data-dir", shared_data, "--json", "--inline-arrays")
    assert code == 0, err
    inline = json.loads(out)["per_query"]
    arrays = per_query(read_results()[-1])
    assert np.array_equal(inline["database_indices"], arrays["database_indices"])
    assert np.array_equal(inline["first_positive_rank"], arrays["first_positive_rank"])


def test_inline_arrays_without_json_is_refused(cli, shared_data):
    code, out, err = cli(*EVALUATE, "--data-dir", shared_data, "--inline-arrays")
    assert code == 1 and out == ""
    assert err.strip() == "error: --inline-arrays is for --json (the record printed as JSON): add --json, or drop it."
