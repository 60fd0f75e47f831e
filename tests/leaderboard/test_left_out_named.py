"""`vprbench leaderboard show` names each run left out of every cell (run id, row label, dataset,
why), as the site's "Runs left out" does: it once printed only a count and one reason, so nobody
could find the run. Past five it counts the rest; names from records print literally."""
from __future__ import annotations

from vprbench.evaluation import read_results, save_result

MARKUP = "[bold red]x[/] :pile_of_poo:"
CONTROLS = "\x1b]0;owned\x07"


def _save(make_record, seeds, **options):
    for seed in seeds:
        save_result(make_record("hog", seed=seed, weights={"source": "random"}, options={"note": f"n{seed}", **options}))


def test_each_left_out_run_is_named(make_record, cli, monkeypatch, tmp_path):
    monkeypatch.setenv("COLUMNS", "300")
    save_result(make_record("hog", seed=9, quality=0.6))  # fills the one cell
    _save(make_record, range(2))
    code, out, _ = cli("leaderboard")
    assert code == 0
    records = {r["run_id"]: r for r in read_results() if r["spec"]["options"].get("note")}
    assert "2 run(s) left out of every cell:" in out
    for run_id, record in records.items():
        line = next(line for line in out.splitlines() if run_id in line)
        assert line.startswith(f"- run {run_id}, hog [note={record['spec']['options']['note']}] on corridor: random weights")
    docs = tmp_path / "docs"
    assert cli("leaderboard", "publish", "--to", docs)[0] == 0
    site = (docs / "leaderboard" / "index.md").read_text().split("## Runs left out")[1]
    for run_id, record in records.items():  # the same names on the site
        assert f"| <code>{run_id}</code> | hog [note={record['spec']['options']['note']}] | corridor | random weights" in site


def test_past_five_the_rest_are_counted(make_record, cli, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")
    save_result(make_record("hog", seed=9, quality=0.6))
    _save(make_record, range(7))
    code, out, _ = cli("leaderboard")
    assert code == 0
    assert "7 run(s) left out of every cell:" in out
    assert sum(line.startswith("- run ") for line in out.splitlines()) == 5
    assert "and 2 more (all under \"Runs left out\"" in out


def test_names_print_literally(make_record, cli, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")
    save_result(make_record("hog", seed=9, quality=0.6))
    _save(make_record, [1], note=f"{MARKUP} {CONTROLS}")
    code, out, _ = cli("leaderboard")
    assert code == 0
    assert f"hog [note={MARKUP} \\x1b]0;owned\\x07] on corridor: random weights" in out
    assert "\x1b" not in out and "\x07" not in out


def test_when_no_run_fills_a_cell_the_error_names_them(make_record, cli, monkeypatch):
    monkeypatch.setenv("COLUMNS", "300")
    _save(make_record, range(2))
    code, _, err = cli("leaderboard")
    assert code == 1 and "Traceback" not in err
    runs = [r["run_id"] for r in read_results()]
    assert "None of the 2 stored run(s) can fill a cell: run " in " ".join(err.split())
    assert len(err.strip().splitlines()) == 1 or "\n- " not in err  # one line (the console may wrap it)
    assert all(run_id in err for run_id in runs) and "random weights" in err


def test_a_run_id_on_the_site_is_escaped_once(make_record, cli, tmp_path):
    """`code` escapes what it is given: the id was escaped before it too, so an '_' Markdown would
    read ('r._x') showed as '&#95;' on the page."""
    save_result(make_record("hog", seed=9, quality=0.6))  # fills the one cell
    record = make_record("hog", seed=1, weights={"source": "random"}, options={"note": "n"})
    record["run_id"] = "r._x"
    save_result(record)
    docs = tmp_path / "docs"
    assert cli("leaderboard", "publish", "--to", docs)[0] == 0
    site = (docs / "leaderboard" / "index.md").read_text().split("## Runs left out")[1]
    assert "| <code>r.&#95;x</code> | hog [note=n] | corridor |" in site and "&amp;" not in site
