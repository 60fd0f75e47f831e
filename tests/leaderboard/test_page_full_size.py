"""A dataset page at the largest query count vprbench serves: Nordland's swapped protocol, 27,592
queries against 2,760 (here as one's own data of that shape, K = 20). Its "Data and ground truth" row
counts positives from the run's arrays (since 2026-12-07)."""
import time

import numpy as np

from vprbench.leaderboard import build_board
from vprbench.leaderboard.site import dataset_page
from vprbench.leaderboard.tables import cell_stats

QUERIES, DATABASE = 27_592, 2_760


def test_dataset_page_at_nordland_swapped_size(make_record, tmp_path):
    record = make_record("hog", "own-nordland", kind="own", n_database=DATABASE, n_queries=QUERIES, unit="frames",
                         radius=1, quality=0.6)
    positives = np.asarray(record["per_query"]["positives"])
    assert positives.shape == (QUERIES,)
    board = build_board([record])
    (tmp_path / "figures").mkdir()
    (tmp_path / "downloads").mkdir()
    started = time.perf_counter()
    page = dataset_page(tmp_path, board, board.columns[0], {key: cell_stats(c) for key, c in board.cells.items()})
    took = time.perf_counter() - started
    row = page.split("## Data and ground truth", 1)[1].splitlines()[4]
    cells = [c.strip() for c in row.strip("|").split(" | ")]
    assert cells[:4] == [str(DATABASE), str(QUERIES), str(int(np.sum(positives == 0))), str(int(positives.sum()))], row
    # the page's download holds the per-query arrays once, compactly: 27,592 x 20 indices and scores are
    # under 40 bytes a pair as JSON; the arrays held twice or as nested lists of floats would not be
    download = tmp_path / "downloads" / f"{board.columns[0].slug}.json"
    assert download.stat().st_size < 40 * QUERIES * 20, download.stat().st_size
    assert took < 60, took  # generous: about 2 s on 2 shared cores; per-query work against every query is hours
