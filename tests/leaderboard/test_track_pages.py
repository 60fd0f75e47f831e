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
