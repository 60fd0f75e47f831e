"""Full-size test trees of the "utm-names" datasets (images/test/{database,queries}, UTM in the
file names, as gmberton/VPR-datasets-downloader formats them), built like tests/pitts30k_tree.py:
one small generated JPEG per distinct position, hard-linked to every name taken there.

- Tokyo 24/7: 75,984 database and 315 query images at their REAL UTM positions (the
  Patch-NetVLAD ground truth in ../shared/data); the names are made up (pano, tile, heading).
- Pitts-250k test: 83,952 database and 8,280 query images at SYNTHETIC positions: Pitts-30k
  test's real positions repeated in blocks 1 km apart (its area spans 556 x 465 m, so no
  positive crosses a block): database blocks 0..8 cut at 83,952, query blocks 0..1 cut at 8,280.

    python tests/utm_trees.py ../shared/data /tmp/trees pitts250k     (or tokyo247)
    vprbench evaluate --method hog --dataset pitts250k --data-dir /tmp/trees
"""
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pitts30k_tree import link_images, place_image

BLOCK_METRES = 1000.0  # > Pitts-30k's extent + the 25 m radius: blocks share no positives


def downloader_coord(value: float, left: int, right: int) -> str:
    """A coordinate as the downloader writes it: zero-padded, decimals cut (not rounded)."""
    sign = "-" if value < 0 else ""
    integer, decimal = f"{abs(value):.10f}".split(".")
    return f"{sign}{int(integer):0{left - len(sign)}d}.{decimal[:right]}"


def downloader_names(utm: np.ndarray, zone: int, letter: str, folder: str, note: str) -> tuple[list, np.ndarray]:
    """`folder/@easting@northing@zone@letter@lat@lon@pano@tile@heading@...@note@.jpg` for each
    position (the i-th image at a position gets tile i), and the positions as written."""
    import utm as utm_module

    lat, lon = utm_module.to_latlon(utm[:, 0], utm[:, 1], zone, letter)
    names, seen, panos = [], {}, {}
    for (easting, northing), la, lo in zip(utm, lat, lon):
        key = (float(easting), float(northing))
        pano = panos.setdefault(key, len(panos))
        tile = seen[key] = seen.get(key, -1) + 1
        names.append(f"{folder}/@{downloader_coord(easting, 7, 2)}@{downloader_coord(northing, 7, 2)}@{zone:02d}@{letter}"
                     f"@{downloader_coord(la, 3, 5)}@{downloader_coord(lo, 4, 5)}@{pano:06d}@{tile:02d}@{30 * tile % 360:03d}"
                     f"@@@@@{note}@.jpg")
    written = np.array([[float(n.split("@")[1]), float(n.split("@")[2])] for n in names])
    return names, written


def build_utm(data: Path, name: str, utm_db: np.ndarray, utm_q: np.ndarray, zone: int, letter: str) -> SimpleNamespace:
    """<data>/<name>/images/test/{database,queries}; names relative to <data>/<name>."""
    db_names, db_written = downloader_names(utm_db, zone, letter, "images/test/database", "")
    q_names, q_written = downloader_names(utm_q, zone, letter, "images/test/queries", "query")
    root = data / name
    made = link_images(root, data / f"pool-{name}", [(db_names, db_written), (q_names, q_written)], place_image)
    return SimpleNamespace(data=data, root=root, db_names=db_names, q_names=q_names,
                           utm_db=db_written, utm_q=q_written, jpegs=made)


def build_tokyo247(shared_data: Path, data: Path) -> SimpleNamespace:
    gt = np.load(shared_data / "ground-truth" / "patchnetvlad" / "tokyo247.npz")
    return build_utm(data, "tokyo247", gt["utmDb"], gt["utmQ"], 54, "S")


def build_pitts250k(shared_data: Path, data: Path) -> SimpleNamespace:
    gt = np.load(shared_data / "ground-truth" / "patchnetvlad" / "pitts30k_test.npz")
    blocks = lambda utm, count: np.vstack([utm + [b * BLOCK_METRES, 0] for b in range(-(-count // len(utm)))])[:count]  # noqa: E731
    return build_utm(data, "pitts250k", blocks(gt["utmDb"], 83952), blocks(gt["utmQ"], 8280), 17, "T")


if __name__ == "__main__":
    tree = {"tokyo247": build_tokyo247, "pitts250k": build_pitts250k}[sys.argv[3]](Path(sys.argv[1]), Path(sys.argv[2]))
    print(f"{tree.root}: {len(tree.db_names)} database and {len(tree.q_names)} query images, {tree.jpegs} JPEGs")
