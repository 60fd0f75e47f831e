"""Recall at 100 % precision is a fraction in the record and shown in percent like Recall@K."""
from rich.console import Console

from vprbench.cli.evaluate import results_table
from vprbench.text import percent


def test_evaluate_table_shows_recall_at_full_precision_in_percent(make_record):
    record = make_record()
    record["recall_at_100_precision"] = 0.123456
    console = Console(width=200, record=True)
    console.print(results_table(record))
    row = [line for line in console.export_text().splitlines() if f"{record['recall']['1']:.1f}" in line][0]
    assert row.split("│")[-2].strip() == "12.3" and "0.123 " not in row
    assert (percent(0.0), percent(1.0), percent(None)) == ("0.0", "100.0", "–")
