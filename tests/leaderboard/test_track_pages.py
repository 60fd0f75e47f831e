"""The track pages (re-ranked, sequence) say of each row what the dataset pages say: its weights and their
licence beside it, and where its number comes from. Before, a re-ranked or sequence run's licence was on no
page of the site, and a contributed run read there as measured here."""
import pytest

from vprbench.leaderboard import build_board
from vprbench.leaderboard.tables import cell_stats
from vprbench.leaderboard.tracks import track_page

LICENCE = "<script>document.title='x'</script> | CC-BY-NC-4.0"


@pytest.mark.parametrize("track, stage", [("re-ranked", {"name": "aqe", "k": 20, "n": 1}),
                                          ("sequence", {"name": "diagonal", "length": 10})])
def test_a_track_page_gives_each_rows_licence_in_its_own_column(make_record, track, stage):
    weights = {"source": "official", "url": "https://example.org/w.pth", "licence": LICENCE}
    board = build_board([make_record("hog", seed=1), make_record("thumb", weights=weights, stages=[stage], seed=2)])
    stats = {key: cell_stats(cell) for key, cell in board.cells.items()}
    table = [line for line in track_page(board, track, stats).splitlines() if line.startswith("|")]
    header, rows = table[0].strip("|").split(" | "), [line.strip("|").split(" | ") for line in table[2:]]
    assert [h.strip() for h in header[:3]] == ["Method", "Weights", "Licence"]
    assert len(rows) == 1 and all(len(row) == len(header) for row in rows)  # the '|' of the licence breaks no cell
    assert rows[0][1].strip() == "official"
    assert rows[0][2].strip() == ("&lt;script&gt;document.title=&#x27;x&#x27;&lt;/script&gt; &#124; CC-BY-NC-4.0")


def test_a_contributed_run_on_a_track_page_carries_its_mark_and_legend(make_record):
    """Before: a sequence run contributed to a results repository read on the track page as a run
    measured here (no <sup>c</sup>, no legend), while its dataset page marked it."""
    theirs = {**make_record("hog", stages=[{"name": "diagonal", "length": 10}], seed=2),
              "_contribution": {"contributor": "A. Lab"}}
    board = build_board([make_record("hog", seed=1), theirs])
    page = track_page(board, "sequence", {key: cell_stats(cell) for key, cell in board.cells.items()})
    row = next(line for line in page.splitlines() if line.startswith("| hog + diagonal"))
    assert row.startswith("| hog + diagonal<sup>c</sup> |"), row
    assert "Marks: <sup>c</sup> contributed to the results repository" in page


def _left_out(page: str) -> list[str]:
    """The rows of a page's "Runs left out" table."""
    section = page.split("## Runs left out", 1)[1].split("\n## ", 1)[0]
    return [line for line in section.splitlines() if line.startswith("| ") and not line.startswith("| Run |")]


def test_a_track_page_lists_the_runs_left_out_of_its_track(make_record):
    """Before: the re-ranked page listed none of the re-ranked runs left out (random weights), which
    only the overview named; a single-image run left out stays off the track page."""
    stage = [{"name": "aqe", "k": 20, "n": 1}]
    random = make_record("thumb", weights={"source": "random"}, stages=stage, seed=3)
    board = build_board([make_record("hog", seed=1), make_record("hog", stages=stage, seed=2), random,
                         make_record("dense-vlad", weights={"source": "random"}, seed=4)])
    page = track_page(board, "re-ranked", {key: cell_stats(cell) for key, cell in board.cells.items()})
    (row,) = _left_out(page)
    assert random["run_id"] in row and "random weights" in row


def test_a_contributed_run_left_out_carries_its_mark(make_record, tmp_path):
    """Before: under "Runs left out" a contributed run read as one measured here (no <sup>c</sup>),
    while its cells were marked."""
    from vprbench.leaderboard.site import overview

    theirs = {**make_record("dense-vlad", weights={"source": "random"}, seed=2), "_contribution": {"contributor": "A. Lab"}}
    board = build_board([make_record("hog", seed=1), theirs, make_record("thumb", weights={"source": "random"}, seed=3)])
    (tmp_path / "figures").mkdir()
    page = overview(tmp_path, board, [], {key: cell_stats(cell) for key, cell in board.cells.items()})
    rows = _left_out(page)
    assert [("<sup>c</sup>" in row) for row in rows] == [True, False], rows
    assert "| dense-vlad<sup>c</sup> |" in rows[0]
    assert "Marks: <sup>c</sup> contributed to a results repository." in page.split("## Runs left out", 1)[1]
