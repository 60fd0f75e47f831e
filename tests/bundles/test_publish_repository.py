"""`leaderboard publish --results DIR`: the site built from a results repository fed by two
contributors' bundles, each row with its contributor, date, hardware and vprbench version, each
cell marked by where its number comes from; `leaderboard show` and `compare` with `--results DIR`
read the very same runs."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from vprbench.bundles import export_bundle, import_bundles
from vprbench.evaluation.rescore import DataGroundTruth
from vprbench.cli.main import main
from vprbench.evaluation import save_result
from vprbench.evaluation.record import PER_QUERY_FIELDS
from vprbench.evaluation.results import per_query
from vprbench.leaderboard.cells import AGREES, CONTRIBUTED, MEASURED


@pytest.fixture
def repository(records, shared_data, tmp_path):
    alice = export_bundle([records[0]], tmp_path / "alice.tar.gz", contributor="alice")
    bob = export_bundle([records[1]], tmp_path / "bob.tar.gz", contributor="bob")
    repo = tmp_path / "repo"
    assert all(r.ok for r in import_bundles([alice, bob], repo, DataGroundTruth(shared_data)))
    return repo


def rerun(record: dict, run_id: str, ranks=None) -> dict:
    """The same run again on this machine (inline arrays; `ranks` replaces its first-positive ranks)."""
    arrays = per_query(record)
    again = {k: v for k, v in record.items() if not k.startswith("_")}
    again["per_query"] = {"k": int(arrays["database_indices"].shape[1]),
                          **{n: arrays[n].tolist() for n in PER_QUERY_FIELDS}}
    if ranks is not None:
        again["per_query"]["first_positive_rank"] = ranks
        again["recall"] = {k: 0.0 for k in again["recall"]}  # no query found: every metric is 0
        again.update(auc_pr=0.0, recall_at_100_precision=0.0, max_f1=0.0)
        # ranks that do not fit its indices: shown only while no ground truth here re-scores them (its copy gone)
        again["dataset_root"] = str(Path(record["dataset_root"]).parent / "moved-away" / "corridor")
    again.update(run_id=run_id, created="2030-01-01T00:00:00+00:00")
    return again


def overview_cells(docs) -> dict:
    """Row name -> its Corridor cell in the overview's Table II, as Markdown."""
    page = (docs / "leaderboard" / "index.md").read_text()
    table = page[page.index("### Table II"):page.index("### Table III")]
    header = next(line for line in table.splitlines() if line.startswith("| Method"))
    at = [c.strip() for c in header.split("|")].index("[corridor](corridor.md)")
    return {cells[1].strip(): cells[at].strip() for line in table.splitlines()
            if line.startswith("| hog") and (cells := line.split("|"))}


def entries(docs) -> dict:
    return {d["method"]: d for d in json.loads((docs / "leaderboard" / "downloads" / "leaderboard.json").read_text())}


def test_a_site_from_a_repository_marks_each_cell(repository, records, tmp_path, capsys):
    docs, empty = tmp_path / "docs", tmp_path / "empty-cache"
    assert main(["leaderboard", "publish", "--to", str(docs), "--results", str(repository), "--cache-dir", str(empty)]) == 0
    found = entries(docs)
    assert set(found) == {"hog", "hog [resize=96x128]"}
    assert {d["source"] for d in found.values()} == {CONTRIBUTED}
    assert {found["hog"]["contributor"], found["hog [resize=96x128]"]["contributor"]} == {"alice", "bob"}
    # was: the intervals' level, resamples and seed only on the pages, not in a download read alone
    assert {d["ci_method"] for d in found.values()} == {"95% percentile bootstrap, 10,000 resamples, seed 0"}
    assert "ci_method" in (docs / "leaderboard" / "downloads" / "corridor.csv").read_text().splitlines()[0]
    page = (docs / "leaderboard" / "corridor.md").read_text()
    for record, who in zip(records, ("alice", "bob")):
        [line] = [row for row in page.splitlines() if f"<code>{record['run_id']}</code>" in row and row.startswith("| hog")]
        assert f"| {CONTRIBUTED} | {who} |" in line and record["created"] in line
        assert record["hardware"]["cpu"] in line and f"| {record['versions']['vprbench']} |" in line
    # the overview marks each contributed cell, and says what the mark means
    assert overview_cells(docs) == {"hog": "**48.6** / **75.7**<sup>c</sup>", "hog [resize=96x128]": "42.3 / 66.7<sup>c</sup>"}
    overview = (docs / "leaderboard" / "index.md").read_text()
    assert "2 cell(s) have runs contributed to a results repository or imported" in overview
    assert "<sup>c</sup> contributed to the results repository, re-scored here from its per-query arrays" in overview
    assert "| hog<sup>c</sup> | none (nothing learnt) |" in page
    # was: "Regenerate with `vprbench leaderboard publish --to docs/`", which without --results drops these runs
    assert "Regenerate with `vprbench leaderboard publish --to docs/ --results DIR` (DIR: the results repository)" \
        in overview

    # this machine re-runs both: one agrees within the contributed run's interval, one does not
    local = tmp_path / "local-cache"
    save_result(rerun(records[0], "20300101T000000Z-rerun-a"), local)
    zeros = [0] * records[1]["counts"]["queries"]
    save_result(rerun(records[1], "20300101T000000Z-rerun-b", ranks=zeros), local)
    assert main(["leaderboard", "publish", "--to", str(docs), "--results", str(repository), "--cache-dir", str(local)]) == 0
    found = entries(docs)
    assert found["hog"]["source"] == AGREES and found["hog"]["contributor"] == "this machine"
    assert found["hog [resize=96x128]"]["source"].startswith("contributed, re-run here and disagreeing: R@1 0.0 here")
    assert found["hog [resize=96x128]"]["r1"] == 0.0  # the newest run fills the cell; the mark says it disagrees
    assert overview_cells(docs) == {"hog": "**48.6** / **75.7**<sup>c✓</sup>", "hog [resize=96x128]": "0.0 / 0.0<sup>c≠</sup>"}

    # only this machine's runs: measured here
    assert main(["leaderboard", "publish", "--to", str(docs), "--cache-dir", str(local)]) == 0
    assert {d["source"] for d in entries(docs).values()} == {MEASURED}
    assert "<sup>" not in (docs / "leaderboard" / "index.md").read_text()
    assert "Regenerate with `vprbench leaderboard publish --to docs/`." in (docs / "leaderboard" / "index.md").read_text()


def shown(capsys, repository, cache, *args) -> str:
    """`leaderboard show --results` over `cache`: its stdout (exit 0)."""
    code = main(["leaderboard", "show", *args, "--results", str(repository), "--cache-dir", str(cache)])
    out, err = capsys.readouterr()
    assert code == 0, err
    return out


def test_show_gives_the_cells_publish_writes_from_a_repository(repository, records, tmp_path, capsys, monkeypatch):
    """Was: 'leaderboard show --results DIR' refused ('--results DIR is for leaderboard publish'): a
    repository's maintainer could not see in the terminal what publish would put on the site."""
    local, docs = tmp_path / "local-cache", tmp_path / "docs"
    same = rerun(records[0], records[0]["run_id"])  # alice's run, on this machine too: one run, this machine's
    same["created"] = records[0]["created"]
    save_result(same, local)
    save_result(rerun(records[1], "20300101T000000Z-rerun-b", ranks=[0] * records[1]["counts"]["queries"]), local)
    assert main(["leaderboard", "publish", "--to", str(docs), "--results", str(repository), "--cache-dir", str(local)]) == 0
    capsys.readouterr()
    published = {m: (d["run_id"], d["source"], d["r1"], d["r5"]) for m, d in entries(docs).items()}
    cells = {s["label"]: (s["run_id"], s["source"], round(s["r1"], 6), round(s["r5"], 6))
             for s in json.loads(shown(capsys, repository, local, "--format", "json"))}
    assert cells == published
    # counted once: not 'contributed, re-run here and agreeing' (its contributed copy beside it)
    assert published["hog"][:2] == (records[0]["run_id"], MEASURED)
    assert published["hog [resize=96x128]"][1].startswith("contributed, re-run here and disagreeing")

    # every other format marks the cells as the site does
    csv = shown(capsys, repository, local, "--format", "csv")
    assert csv.strip().splitlines()[1:] == ["hog,none (nothing learnt),–,48.6 / 75.7", "hog [resize=96x128],none (nothing learnt),–,0.0 / 0.0 c≠"]
    markdown = shown(capsys, repository, local, "--format", "markdown")
    assert "| 48.6 / 75.7 " in markdown and "| 0.0 / 0.0<sup>c≠</sup> " in markdown
    assert markdown.rstrip().endswith("Marks: <sup>c≠</sup> contributed, and re-run here outside its interval.")
    monkeypatch.setenv("COLUMNS", "300")
    terminal = shown(capsys, repository, tmp_path / "empty-cache")
    assert "│ 48.6 / 75.7 c │" in terminal and "│ 42.3 / 66.7 c │" in terminal
    assert "Marks: c: contributed to the results repository, re-scored here from its per-query arrays." in terminal


def test_compare_sets_a_contributed_run_against_a_local_one(repository, records, shared_data, tmp_path, capsys):
    local = tmp_path / "local-cache"
    same = rerun(records[0], records[0]["run_id"])
    same["created"] = records[0]["created"]
    save_result(same, local)
    compare = ["leaderboard", "compare", "hog", "hog [resize=96x128]", "--dataset", "corridor", "--cache-dir", str(local),
               "--data-dir", str(shared_data)]
    assert main(compare) == 1  # bob's run is in the repository only
    assert "No run of 'hog [resize=96x128]' on corridor" in capsys.readouterr().err
    assert main([*compare, "--results", str(repository)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].endswith(f"run {records[0]['run_id']}") and f"R@1 {records[0]['recall']['1']:5.1f} %" in lines[1]
    assert lines[2].endswith(f"run {records[1]['run_id']} (c: contributed, re-scored, sent by bob)")
    assert f"R@1 {records[1]['recall']['1']:5.1f} %" in lines[2]


def test_show_and_compare_report_a_repositorys_unreadable_and_refused_records(repository, shared_data, tmp_path, cli):
    from bundles.test_cells_rescored import _forge_perfect
    from vprbench.bundles import read_repository

    [first, _] = read_repository(repository)
    damaged = Path(first["_source"]).with_name("20300101T000000Z-damaged.json")
    damaged.write_text("{not json")
    args = ["--results", repository, "--cache-dir", tmp_path / "empty-cache", "--data-dir", shared_data]
    with pytest.warns(UserWarning, match=f"{damaged}"):  # named in a warning, as publish names it
        code, out, err = cli("leaderboard", "compare", "hog", "hog [resize=96x128]", "--dataset", "corridor", *args)
    assert code == 1 and "Traceback" not in err and "R@1" in out
    assert "1 stored file(s) could not be read" in err and "nothing was deleted" in err
    forged = _forge_perfect(first)
    with pytest.warns(UserWarning) as said:
        code, out, err = cli("leaderboard", "show", "--format", "csv", *args)
    assert code == 1 and "Traceback" not in err and "100.0" not in out
    assert any(f"{forged}: its per-query top-K indices do not re-score" in str(w.message) for w in said)
    assert "1 run(s) do not re-score to their numbers" in err and "1 stored file(s) could not be read" in err


@pytest.mark.parametrize("action", [["show"], ["show", "--format", "json"], ["compare", "hog", "sad", "--dataset", "corridor"],
                                    ["publish", "--to", "{tmp}/docs"]])
@pytest.mark.parametrize("kind, said", [("nowhere", "does not exist"), ("empty", "holds no records"),
                                        ("file", "is a file, not a folder")])
def test_a_folder_that_is_no_repository_is_refused_in_one_line(action, kind, said, tmp_path, cli):
    results = tmp_path / kind
    results.mkdir() if kind == "empty" else results.write_text("x") if kind == "file" else None
    code, out, err = cli("leaderboard", *[a.format(tmp=tmp_path) for a in action], "--results", results)
    assert code == 1 and out == "" and "Traceback" not in err
    assert err.count("\n") == 1 and f"error: The results repository {results} {said}: give the folder" in err
    assert not (tmp_path / "docs").exists()
