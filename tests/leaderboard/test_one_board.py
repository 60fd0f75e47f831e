"""One computed board, rendered to every format: the CLI table, Markdown, CSV and JSON, the site's
pages and its downloads show the same cells, parsed back and compared. A column is one protocol of
one dataset, own data included: a traverse evaluated with ±1 and ±10 frames is two columns, each
with its own numbers, and the same heading names it in `compare`."""
from __future__ import annotations

import io
import json
import re

import pandas as pd
import pytest

from vprbench.cli.main import main
from vprbench.evaluation import read_results, save_result
from vprbench.leaderboard import build_board, computed, publish
from vprbench.leaderboard.escape import text

ONE, TEN = "my-traverse (own, ±1 frame)", "my-traverse (own, ±10 frames)"
#: a licence as a record declares it (AnyLoc: its backbone's), hostile: escaped wherever it is shown
LICENCE = "Licence <b>x</b> | [y](javascript:z)"
LICENCES = {"hog": "–", "dense-vlad": f"{LICENCE} (gated)", "netvlad": "–"}


@pytest.fixture
def runs(make_record, tmp_path):
    """hog and dense-vlad on one traverse with ±1 and ±10 frames, netvlad on ±1 only, hog on Corridor."""
    root = tmp_path / "my-traverse"
    own = dict(dataset="my-traverse", kind="own", unit="frames", n_database=60, n_queries=60, root=root,
               fingerprint="fp-my-traverse")
    found = {("hog", ONE): make_record("hog", radius=1, quality=0.35, seed=1, **own),
             ("hog", TEN): make_record("hog", radius=10, quality=0.55, seed=2, **own),
             ("dense-vlad", ONE): make_record("dense-vlad", radius=1, quality=0.6, seed=3, **own),
             ("dense-vlad", TEN): make_record("dense-vlad", radius=10, quality=0.8, seed=4, **own),
             ("netvlad", ONE): make_record("netvlad", radius=1, quality=0.2, seed=5, **own),
             ("hog", "corridor"): make_record("hog", quality=0.5, seed=6)}
    for (method, _), record in found.items():
        if method == "dense-vlad":
            record["provenance"]["backbone"] = {"name": "x", "licence": LICENCE, "gated": True}
        save_result(record)
    return found


def expected(runs) -> dict:
    return {key: (f"{r['recall']['1']:.1f}", f"{r['recall']['5']:.1f}") for key, r in runs.items()}


def _pipe_table(lines: list[str]) -> list[list[str]]:
    return [[c.strip() for c in re.split(r"(?<!\\)\|", line.strip())[1:-1]] for line in lines
            if line.strip().startswith("|") and not re.match(r"^\|[\s:|-]+\|$", line.strip())]


def from_grid(header: list[str], rows: list[list[str]]) -> dict:
    """(label, column) -> (R@1, R@5) from a methods x datasets grid of 'R@1 / R@5'."""
    found = {}
    for row in rows:
        label = row[0].split(" † ")[0]
        for title, value in zip(header[3:], row[3:]):
            if value not in ("-", ""):
                found[(label, title)] = tuple(v.strip() for v in value.split("/"))
    return found


def cli(capsys, *args) -> str:
    assert main(["leaderboard", *args]) == 0
    return capsys.readouterr().out


def test_every_format_shows_the_same_board(runs, capsys, tmp_path, monkeypatch):
    want = expected(runs)
    board = build_board(read_results())
    assert [c.title for c in board.columns] == ["corridor", ONE, TEN]
    assert len({c.key for c in board.columns}) == 3

    # the computed board itself, and JSON
    assert {(s.label, s.column): (f"{s.r1:.1f}", f"{s.r5:.1f}") for s in computed(board)} == want
    assert {s.label: s.licence for s in computed(board)} == LICENCES
    shown = json.loads(cli(capsys, "--format", "json"))
    assert {(s["label"], s["column"]): (f"{s['r1']:.1f}", f"{s['r5']:.1f}") for s in shown} == want
    assert {s["source"] for s in shown} == {"measured here"} and {s["label"]: s["licence"] for s in shown} == LICENCES

    # CSV and Markdown
    frame = pd.read_csv(io.StringIO(cli(capsys, "--format", "csv")), dtype=str).fillna("")
    assert from_grid(list(frame.columns), frame.values.tolist()) == want
    assert frame.set_index("method").loc["netvlad", TEN] == "-"  # run only on ±1: nothing under ±10
    assert dict(frame[["method", "licence"]].values) == LICENCES
    markdown = cli(capsys, "--format", "markdown")
    [header, *rows] = _pipe_table(markdown.splitlines())
    assert from_grid(header, rows) == want
    assert header[2] == "licence" and {r[0]: r[2] for r in rows} == {k: text(v) for k, v in LICENCES.items()}
    assert "<b>" not in markdown and "](javascript" not in markdown

    # the terminal table (wide enough not to wrap)
    monkeypatch.setenv("COLUMNS", "300")
    terminal = cli(capsys)
    lines = [line for line in terminal.splitlines() if "│" in line or "┃" in line]
    table = [[c.strip() for c in re.split("[│┃]", line)[1:-1]] for line in lines]
    assert from_grid(table[0], table[1:]) == want
    assert table[0][2] == "licence" and {r[0]: r[2] for r in table[1:]} == LICENCES

    # the site: each column's page, the overview's tables, and the downloads
    out = publish(tmp_path / "docs")
    site = {}
    for column in board.columns:
        page = (out / f"{column.slug}.md").read_text()
        assert next(line for line in page.splitlines() if line.startswith("# ")) == f"# {column.title}"
        results = page.split("## Results")[1].split("The runs in the cells above")[0].splitlines()
        for row in _pipe_table(results)[1:]:
            site[(row[0].rstrip(" †"), column.title)] = tuple(v.split(" [")[0] for v in row[3:5])
            assert row[2] == text(LICENCES[row[0].rstrip(" †")])
    assert site == want
    overview = (out / "index.md").read_text()
    others = _pipe_table(overview.split("## Other runs")[1].split("## Runs left out")[0].splitlines())
    assert {(r[0], re.sub(r"^\[(.*)\]\(.*\)$", r"\1", r[3])): tuple(v.split(" [")[0] for v in r[4:6])
            for r in others[1:]} == {k: v for k, v in want.items() if k[1] != "corridor"}
    assert {r[0]: r[2] for r in others[1:]} == {k: text(v) for k, v in LICENCES.items()}
    assert "<b>" not in overview and "](javascript" not in overview
    download = json.loads((out / "downloads" / "leaderboard.json").read_text())
    assert {(d["method"], d["column"]): (f"{d['r1']:.1f}", f"{d['r5']:.1f}") for d in download} == want
    assert {d["method"]: d["licence"] for d in download} == LICENCES
    csv = pd.read_csv(out / "downloads" / "leaderboard.csv")
    assert {(m, c): (f"{a:.1f}", f"{b:.1f}") for m, c, a, b in csv[["method", "column", "r1", "r5"]].values} == want


def test_compare_takes_the_heading_every_table_shows(runs, capsys):
    assert main(["leaderboard", "compare", "hog", "dense-vlad", "--dataset", TEN]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{TEN}: R@1 of two runs over the same 60 queries")
    assert f"R@1 {runs[('hog', TEN)]['recall']['1']:5.1f} %" in out
    assert f"R@1 {runs[('dense-vlad', TEN)]['recall']['1']:5.1f} %" in out

    for label, why in (("my-traverse", "Several columns are datasets named 'my-traverse'"),
                       ("my-travers", "No run on dataset 'my-travers' fills a cell")):
        assert main(["leaderboard", "compare", "hog", "dense-vlad", "--dataset", label]) == 1
        err = capsys.readouterr().err
        assert why in err and f"'{ONE}'" in err and f"'{TEN}'" in err and "'corridor'" in err


def test_console_tables_print_names_as_they_are(make_record, capsys, monkeypatch):
    """A row named like Rich markup prints as written, not styled or swallowed."""
    save_result(make_record("hog", options={"resize": [64, 64]}, seed=1))
    record = make_record("[bold red]x[/bold red]", seed=2)
    save_result(record)
    monkeypatch.setenv("COLUMNS", "300")
    out = cli(capsys)
    assert "[bold red]x[/bold red]" in out and "hog [resize=64x64]" in out
