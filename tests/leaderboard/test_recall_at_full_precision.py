"""Recall at 100 % precision is a fraction in the record and shown in percent like Recall@K."""
from rich.console import Console

from vprbench.cli.evaluate import results_table
from vprbench.text import percent


def test_evaluate_table_shows_recall_at_full_precision_in_percent(make_record):
    record = make_record()
    record["recall_at_100_precision"] = 0.123456
    console = Console(width=200, record=True)
    console.print(results_table(record))
    lines = console.export_text().splitlines()
    header = [cell.strip() for cell in next(line for line in lines if "R@100%P" in line).split("┃")]
    row = [cell.strip() for cell in next(line for line in lines if f"{record['recall']['1']:.1f}" in line).split("│")]
    assert row[header.index("R@100%P")] == "12.3" and "0.123" not in row
    assert (percent(0.0), percent(1.0), percent(None)) == ("0.0", "100.0", "–")


def test_the_sequence_page_names_the_curve_its_pr_metrics_are_from():
    # they are VPR-Bench's (recall over the correct top-1 matches); the page called them the robotics'
    # convention, whose recall is over the queries with a positive (HOG on Corridor: R@100%P 5.6 against 2.7)
    from vprbench.leaderboard.tracks import INTRO

    assert "VPR-Bench's precision-recall curve" in INTRO["sequence"] and "robotics convention" not in INTRO["sequence"]
