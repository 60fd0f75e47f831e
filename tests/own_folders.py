"""Folders of one's own made from the real corridor images, for tests of the own-data route."""
from __future__ import annotations

import os
from pathlib import Path


def corridor_folder(shared_data: Path, own: Path, database: int = 3, queries: int = 2, first: int = 0) -> Path:
    """The first `database` reference and `queries` query images of corridor, linked into `own`,
    placed 10 m apart along x (image i of either split at x = 10 i); `first`: of corridor's images from that one on."""
    rows = ["image,x,y"]
    for split, folder, count in (("database", "ref", database), ("queries", "query", queries)):
        (own / split).mkdir(parents=True)
        for i in range(count):
            name = f"{i:07d}.jpg"
            os.symlink(shared_data / "corridor" / folder / f"{first + i:07d}.jpg", own / split / name)
            rows.append(f"{split}/{name},{i * 10},0")
    (own / "positions.csv").write_text("\n".join(rows) + "\n")
    return own
