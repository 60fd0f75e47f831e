"""The leaderboard's downloads: one summary row per cell (CSV/JSON) and each cell's full record,
every text from data made public (no path of the publisher's machine)."""
from __future__ import annotations

import json

import numpy as np

from ..evaluation.blocks import for_record
from ..evaluation.metrics import RECALL_DECIMALS
from .cells import CELL_KS, Cell
from .escape import public_data
from .shown import descriptor_bytes, hardware_of, licence_shown, weights_shown
from .stats import LEVEL, RESAMPLES
from .tracks import track_file


def plain(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(type(value).__name__)


def decimals(value):
    """A recall or an interval's end as the downloads give it: the records' RECALL_DECIMALS (6), where
    an interval's end came as a full float (34.54545454545455); the pages show one decimal."""
    return None if value is None else round(float(value), RECALL_DECIMALS)


def page_of(cell: Cell) -> str:
    """The page that shows the cell: its column's, or its track's (a re-ranked or sequence run is on no
    dataset page, site.write_section)."""
    return f"{cell.column.slug}.md" if cell.row.track == "single-image" else track_file(cell.row.track)


def summary(cell: Cell, stats: dict, seed: int = 0) -> dict:
    """One cell's row of the downloads; `stats` as `tables.cell_stats` drew them with `seed`."""
    r = cell.record
    entry = {"row": cell.row.name, "method": cell.row.label, "weights": weights_shown(cell.row, r), "licence": licence_shown(r),
             "dataset": cell.column.dataset,
             "column": cell.column.title, "page": page_of(cell), "dataset_kind": cell.column.kind,
             "domain": cell.column.domain, "row_key": cell.row.key, "track": cell.row.track}
    for k in CELL_KS:
        entry[f"r{k}"] = decimals(stats[k]["value"])
        entry[f"r{k}_ci_low"], entry[f"r{k}_ci_high"] = (decimals(end) for end in stats[k]["ci"] or (None, None))
    for k in (10, 20):
        entry[f"r{k}"] = decimals(cell.recall(k))
    entry.update({key: r.get(key) for key in ("auc_pr", "recall_at_100_precision", "max_f1", "descriptor_dim")})
    entry["descriptor_bytes"] = descriptor_bytes(r)  # as the pages give it
    entry.update({key: r.get(key) for key in ("run_id", "created", "dataset_fingerprint")})
    entry["images_per_second"], entry["speed_hardware"] = cell.images_per_second, cell.hardware
    entry["source"], entry["hardware"] = cell.source, hardware_of(r)
    entry["contributor"] = (r.get("_contribution") or {}).get("contributor") or "this machine"
    entry["speed_run_id"] = (cell.timed or {}).get("run_id")
    # as the dataset page gives it, id and hash: one own folder's ±1 and ±10 frames share the id 'name:own'
    entry["protocol"], entry["protocol_hash"] = (r.get("protocol") or {}).get("id"), cell.column.protocol_hash or None
    entry["ci_resampling"] = for_record(r, cell.arrays).text()  # which queries the intervals draw together
    entry["ci_method"] = f"{LEVEL:.0%} percentile bootstrap, {RESAMPLES:,} resamples, seed {seed}"  # a file read alone says it
    entry["vprbench"] = (r.get("versions") or {}).get("vprbench")
    entry["provenance"] = json.dumps(r.get("provenance") or {}, sort_keys=True)
    return public_data(entry)


def record_download(cell: Cell) -> dict:
    arrays = cell.arrays is not None  # written from the arrays below, not walked by public_data
    record = public_data({k: v for k, v in cell.record.items() if not k.startswith("_") and not (arrays and k == "per_query")})
    if arrays:
        record["per_query"] = {"k": int(cell.arrays["database_indices"].shape[1]),
                               **{name: array.tolist() for name, array in cell.arrays.items()}}
    return record
