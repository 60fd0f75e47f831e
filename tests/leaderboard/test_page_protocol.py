"""A dataset page's "Data and ground truth" says what vprbench ships for the column's protocol and what
the run's arrays hold, never what a record claims beside them: before, a record edited by hand (or
contributed) put its own protocol description, source, radius and counts on the benchmark's page, with
no warning, as nothing checks those fields against the protocol hash that chose the column."""
import numpy as np

from vprbench.evaluation.identity import benchmark_protocols
from vprbench.leaderboard import build_board
from vprbench.leaderboard.site import dataset_page
from vprbench.leaderboard.tables import cell_stats


def test_a_benchmark_page_gives_the_shipped_protocol_and_counts_from_the_arrays(make_record, tmp_path):
    record = make_record("hog", "corridor", seed=1)
    shipped = benchmark_protocols("corridor")[record["protocol"]["hash"]]
    positives = np.asarray(record["per_query"]["positives"])
    record["protocol"] = {**record["protocol"], "description": "FAKE radius of 50 frames", "source": "FAKE source"}
    record["ground_truth"] = {"unit": "positives", "radius": 50, "radius_unit": "frames"}
    record["counts"] = {**record["counts"], "positive_pairs": 99999, "queries_without_positives": 7}
    board = build_board([record])
    (tmp_path / "figures").mkdir()
    (tmp_path / "downloads").mkdir()
    page = dataset_page(tmp_path, board, board.columns[0], {key: cell_stats(c) for key, c in board.cells.items()})
    assert "FAKE" not in page and "99999" not in page and "radius 50" not in page
    row = page.split("## Data and ground truth", 1)[1].splitlines()[4]
    cells = [c.strip() for c in row.strip("|").split(" | ")]
    assert cells[2:4] == [str(int(np.sum(positives == 0))), str(int(positives.sum()))], row
    assert cells[5] == f"positives, radius {shipped['ground_truth']['radius']} frames", row
    assert "Zaffar et al., VPR-Bench, IJCV 2021" in page
