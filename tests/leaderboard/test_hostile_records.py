"""Records are data anyone can hand over (a results repository, a copied cache): a number the
leaderboard shows that is not a number refuses that record at read (its file and field named, the
file kept) instead of failing the publish of every other one; and no text of a record becomes a
formula in a spreadsheet opening a CSV download or export."""
import csv
import io
import json
import math

import pandas as pd
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results, save_result
from vprbench.leaderboard.escape import to_csv

#: (field, value) a hostile record holds; each was read as it was before the fields were typed
NOT_NUMBERS = [
    ("images_per_second", "fast"), ("images_per_second", [1]), ("images_per_second", True),
    ("images_per_second", math.nan), ("images_per_second", math.inf), ("images_per_second", -1.0),
    ("descriptor_dim", "x"), ("descriptor_dim", True), ("descriptor_dim", 1.5), ("descriptor_dim", -64),
    ("descriptor_bytes", "256"), ("descriptor_bytes", math.nan),
    ("descriptors_computed", ["x"]), ("descriptors_computed", {"database": "x", "queries": 0}),
    ("descriptors_computed", {"database": True, "queries": 0}),
    ("auc_pr", "x"), ("auc_pr", math.nan), ("auc_pr", 2.0),
    ("recall_at_100_precision", math.inf), ("max_f1", [0.5]),
    ("timings", {"total_s": math.nan}), ("timings", {"total_s": "1"}),
    ("counts", "queries=True"), ("recall", "1=nan"),
    ("stages", math.nan), ("stages", [{"ms_per_query": math.inf}]), ("stages", [{"candidates_in": "20"}]),
    ("hardware", {"cpu_count": "many"}), ("hardware", {"memory_gib": math.inf}),
    ("per_query", "k=x"),
    # finite, but past what any run measures: a figure's log axis overflowed drawing them
    ("images_per_second", 1e300), ("descriptor_bytes", 10**400), ("stages", [{"ms_per_query": 1e308}]),
]


def _spoil(path, field, value) -> None:
    """The stored record at `path` with `field` set to `value` ('key=x': one entry of it), as a hand
    or another program would write it (Python's JSON writes NaN and Infinity, and reads them)."""
    data = json.loads(path.read_text())
    if isinstance(value, str) and "=" in value and isinstance(data[field], dict):
        key, raw = value.split("=")
        data[field][key] = {"True": True, "nan": math.nan}.get(raw, raw)
    else:
        data[field] = value
    path.write_text(json.dumps(data))


@pytest.mark.parametrize("field, value", NOT_NUMBERS, ids=[f"{f}-{v!r}"[:48] for f, v in NOT_NUMBERS])
def test_a_record_whose_shown_number_is_no_number_is_skipped_at_read(make_record, field, value):
    good = save_result(make_record("hog", seed=2))
    bad = save_result(make_record("sift", seed=1))
    _spoil(bad, field, value)
    skipped: list = []
    with pytest.warns(UserWarning) as caught:
        records = read_results(skipped=skipped)
    assert [r["_source"] for r in records] == [str(good)]
    assert skipped == [bad] and bad.is_file()  # left out, never deleted
    said = " ".join(str(w.message) for w in caught)
    assert str(bad) in said and f"({field}" in said and "Skipped (nothing was deleted)" in said, said


def test_real_records_read_back_with_their_numbers(make_record):
    """A record as the pipeline and an import write it (no descriptor size) reads back unchanged."""
    record = make_record("hog", seed=1)
    imported = make_record("sift", seed=2)
    imported.update(descriptor_dim=None, descriptor_bytes=None, images_per_second=None)
    imported.pop("max_f1")  # older records lack it: it stays absent, not None
    for made in (record, imported):
        save_result(made)
    first, second = read_results()
    assert first["descriptor_dim"] == 64 and first["descriptor_bytes"] == 256 and first["images_per_second"] > 0
    assert first["descriptors_computed"] == record["descriptors_computed"] and first["timings"] == record["timings"]
    assert second["descriptor_dim"] is None and "max_f1" not in second


def test_publish_leaves_hostile_records_out_and_publishes_the_others(make_record, tmp_path, capsys):
    """Each of these made `leaderboard publish` end in a traceback, so one record stopped the whole site."""
    good = make_record("hog", seed=1)
    save_result(good)
    hostile = {"sift": ("images_per_second", "fast"), "orb": ("descriptors_computed", ["x"]),
               "surf": ("descriptors_computed", {"database": "x", "queries": 0}), "brief": ("stages", math.nan),
               "akaze": ("images_per_second", 1e300), "kaze": ("descriptor_bytes", 10**400)}
    paths = {}
    for seed, (method, (field, value)) in enumerate(hostile.items(), start=2):
        paths[method] = save_result(make_record(method, seed=seed))
        _spoil(paths[method], field, value)
    docs = tmp_path / "docs"
    with pytest.warns(UserWarning) as caught:
        code = main(["leaderboard", "publish", "--to", str(docs)])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err, err  # 1: files left unread, named (cli/leaderboard.py `unread`)
    assert f"{len(hostile)} stored file(s) could not be read" in err and "nothing was deleted" in err
    said = " ".join(str(w.message) for w in caught)
    for method, path in paths.items():
        assert str(path) in said and f"({hostile[method][0]}" in said and path.is_file(), method
    pages = " ".join(p.read_text() for p in (docs / "leaderboard").rglob("*.md"))
    assert good["run_id"] in pages
    assert not any(path.stem in pages for path in paths.values())


#: text a spreadsheet would run as a formula, one beginning of each kind
FORMULAS = ["=1+2", "+1+2", "-1+2", "@SUM(1,2)", "\t=1+2", "\r=1+2"]
#: a carriage return inside a cell: unquoted, a spreadsheet ends the row there and reads a formula after it
INSIDE = "MIT\r=1+2"


def _licensed(make_record, **kind):
    methods = ("hog", "sift", "orb", "surf", "brief", "akaze", "kaze")
    for seed, (method, licence) in enumerate(zip(methods, [*FORMULAS, INSIDE]), start=1):
        record = make_record(method, seed=seed, **kind)
        record["provenance"]["backbone"] = {"name": "net", "licence": licence}
        save_result(record)


def test_csv_downloads_keep_formulas_from_records_as_text(make_record, tmp_path, capsys):
    _licensed(make_record)
    docs = tmp_path / "docs"
    assert main(["leaderboard", "publish", "--to", str(docs)]) == 0, capsys.readouterr().err
    downloads = sorted((docs / "leaderboard" / "downloads").glob("*.csv"))
    assert [p.name for p in downloads] == ["corridor.csv", "leaderboard.csv"]
    for path in downloads:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = list(csv.DictReader(handle))
        assert sorted(r["licence"] for r in rows) == sorted(["'" + f for f in FORMULAS] + [INSIDE]), path
        for row in rows:  # numbers stay numbers
            assert float(row["r1"]) >= 0 and int(row["descriptor_dim"]) == 64, path


def test_the_csv_export_keeps_formulas_from_records_as_text(make_record, capsys):
    """`vprbench leaderboard --format csv`: licences, and a dataset name in the header row."""
    _licensed(make_record, dataset="=cmd", kind="own", n_database=40, n_queries=30, fingerprint="fp-x")
    assert main(["leaderboard", "--format", "csv"]) == 0
    rows = [row for row in csv.reader(io.StringIO(capsys.readouterr().out)) if row]  # print adds a line
    header = rows[0]
    assert header[:3] == ["method", "weights", "licence"] and header[3].startswith("'=cmd"), header
    # a carriage return is written out as text first (text.literal): that cell begins with no formula
    assert sorted(r[2] for r in rows[1:]) == sorted(["'" + f for f in FORMULAS[:-1]] + ["\\x0d=1+2", "MIT\\x0d=1+2"])


def test_numbers_stay_numbers_and_only_formula_text_is_quoted():
    frame = pd.DataFrame({"value": [-1.5, 2, None], "name": ["-1.5", "a-b", "-"]}, index=["=x", "y", "z"])
    rows = list(csv.reader(io.StringIO(to_csv(frame))))
    assert rows == [["", "value", "name"], ["'=x", "-1.5", "'-1.5"], ["y", "2.0", "a-b"], ["z", "", "-"]]


#: `created` values that are no UTC time as vprbench writes it: runs are ordered by this text, so each sorted
#: after every real run (or, '+02:00', two hours late) and kept its cell from the runs made after it
NOT_TIMES = ["<script>document.title='x'</script>", "z", "2026-01-01T05:00:00+02:00", "2026-13-01T00:00:00+00:00",
             "2026-01-01"]


@pytest.mark.parametrize("value", NOT_TIMES, ids=[repr(v)[:24] for v in NOT_TIMES])
def test_a_record_whose_time_is_no_utc_time_is_skipped_and_fills_no_cell(make_record, value):
    from vprbench.leaderboard import build_board

    bad = save_result(make_record("hog", seed=1, created="2026-01-01T00:00:00+00:00"))
    good = save_result(make_record("hog", seed=2, created="2026-01-01T04:00:00.500+00:00"))
    _spoil(bad, "created", value)
    with pytest.warns(UserWarning, match=r"\(created: .*should be a UTC time"):
        records = read_results(skipped=(skipped := []))
    assert skipped == [bad] and [r["_source"] for r in records] == [str(good)]
    (cell,) = build_board(records).cells.values()
    assert cell.record["_source"] == str(good)
