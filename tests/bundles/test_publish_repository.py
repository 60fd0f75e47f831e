"""`leaderboard publish --results DIR`: the site built from a results repository fed by two
contributors' bundles, each row with its contributor, date, hardware and vprbench version, each
cell marked by where its number comes from."""
from __future__ import annotations

import json

import pytest

from vprbench.bundles import export_bundle, import_bundles
from vprbench.bundles.verify import DataGroundTruth
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


def test_results_is_refused_outside_publish_and_a_missing_repository_is_named(tmp_path, capsys):
    assert main(["leaderboard", "--results", str(tmp_path)]) == 1
    assert "--results DIR is for 'leaderboard publish'" in capsys.readouterr().err
    assert main(["leaderboard", "publish", "--to", str(tmp_path / "docs"), "--results", str(tmp_path / "nowhere")]) == 1
    assert "nowhere does not exist" in capsys.readouterr().err
