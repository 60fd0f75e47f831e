"""Result records -> methods x datasets tables (terminal, Markdown, CSV) and a docs page."""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path

import pandas as pd

from .errors import VPRBenchError
from .evaluation.record import read_results

FORMATS = ("table", "markdown", "csv")
#: options that change how a run is computed, not what it computes
UNLABELLED_OPTIONS = {"device", "batch_size", "weights"}


def method_label(record: dict) -> str:
    """The method name, with the options the user set on top of its preset: ablations get rows of their own."""
    options = {k: v for k, v in record.get("method_options", {}).items() if k not in UNLABELLED_OPTIONS}
    if not options:
        return record["method"]
    shown = " ".join(f"{k}={'x'.join(map(str, v)) if isinstance(v, list) else v}" for k, v in sorted(options.items()))
    return f"{record['method']} [{shown}]"


def latest_results(records: list[dict]) -> pd.DataFrame:
    """One row per (method, dataset): the newest record."""
    if not records:
        return pd.DataFrame(columns=["method", "dataset", "r1", "r5", "created"])
    rows = [{"method": method_label(r), "dataset": r["dataset"], "created": r["created"],
             "r1": r["recall"].get("1"), "r5": r["recall"].get("5"), "auc_pr": r.get("auc_pr"),
             "version": r.get("versions", {}).get("vprbench"), "device": (r.get("hardware") or {}).get("cuda") or "cpu"}
            for r in records]
    frame = pd.DataFrame(rows).sort_values("created")
    return frame.groupby(["method", "dataset"], as_index=False).last()


def leaderboard(records: list[dict]) -> pd.DataFrame:
    """Methods as rows, datasets as columns, cells 'R@1 / R@5'."""
    latest = latest_results(records)
    if latest.empty:
        return pd.DataFrame()
    latest["cell"] = [_cell(r1, r5) for r1, r5 in zip(latest["r1"], latest["r5"])]
    table = latest.pivot(index="method", columns="dataset", values="cell").fillna("-")
    table.columns.name = None
    return table


def _cell(r1, r5) -> str:
    fmt = lambda v: "-" if v is None or pd.isna(v) else f"{v:.1f}"  # noqa: E731
    return f"{fmt(r1)} / {fmt(r5)}"


def render(table: pd.DataFrame, fmt: str) -> str:
    if fmt not in FORMATS:
        raise VPRBenchError(f"Unknown leaderboard format {fmt!r}; use one of {', '.join(FORMATS)}")
    if fmt == "csv":
        return table.to_csv()
    return table.to_markdown()


def publish(folder: Path, cache_dir=None) -> Path:
    """Write <folder>/leaderboard.md from the results store."""
    records = read_results(cache_dir)
    if not records:
        raise VPRBenchError("No results yet: run 'vprbench evaluate --method M --dataset D' first.")
    folder.mkdir(parents=True, exist_ok=True)
    latest = latest_results(records)
    lines = [
        "# Leaderboard",
        "",
        "Recall@1 / Recall@5 (%) of the newest evaluation of each method on each dataset, "
        "as measured by `vprbench evaluate` (regenerate with `vprbench leaderboard publish --to docs/`).",
        "",
        leaderboard(records).to_markdown(),
        "",
        "## Runs",
        "",
        latest[["method", "dataset", "r1", "r5", "auc_pr", "created", "version", "device"]].to_markdown(index=False),
        "",
        f"_Written {datetime.now(timezone.utc).date().isoformat()}._",
        "",
    ]
    path = folder / "leaderboard.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path
