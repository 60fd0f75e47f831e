"""A full-size Pitts-30k test tree built from the real ground truth in ../shared/data: the real
file names and UTM positions, small generated images. Used by the tests' `pitts30k_tree`
fixture and the benchmarks; to build one by hand (e.g. to time an evaluation):

    python tests/pitts30k_tree.py ../shared/data /tmp/p30k
    vprbench evaluate --method hog --dataset pitts30k --data-dir /tmp/p30k
"""
import os
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from PIL import Image


def place_image(easting: float, northing: float, size=(64, 48), grain: float = 0.0) -> np.ndarray:
    """RGB gratings (64x48 by default) whose phases and angles drift with position (nearby places
    look alike); `grain` adds seeded noise so a JPEG is as large as a photo's."""
    width, height = size
    y, x = np.mgrid[0:height, 0:width] / float(height)
    angle = (easting + northing) / 400.0
    a = np.sin(2 * np.pi * (3 * (x * np.cos(angle) + y * np.sin(angle)) + easting / 150.0))
    b = np.sin(2 * np.pi * (2 * (x * np.sin(angle) - y * np.cos(angle)) + northing / 170.0))
    grey = 127 + 60 * a + 50 * b
    if grain:
        grey = grey + np.random.default_rng(int(abs(easting * 10 + northing))).normal(0, grain, grey.shape)
    return np.stack([grey, np.roll(grey, 7, axis=1), 255 - grey], axis=-1).clip(0, 255).astype(np.uint8)


def link_images(root: Path, pool: Path, groups, image) -> int:
    """Writes one JPEG (`image(easting, northing)` -> RGB uint8) per distinct position into `pool`
    and hard-links it to every `root / name` taken there (`groups`: (names, (N, 2) positions)
    pairs), so a tree of 100k names costs a few thousand small files. Returns the JPEGs made."""
    pool.mkdir(parents=True)
    made_folders, pooled = set(), {}
    for names, utm in groups:
        for name, (easting, northing) in zip(names, utm):
            key = (float(easting), float(northing))
            if key not in pooled:
                pooled[key] = pool / f"{len(pooled)}.jpg"
                Image.fromarray(image(*key)).save(pooled[key], quality=90)
            path = root / name
            if path.parent not in made_folders:
                path.parent.mkdir(parents=True, exist_ok=True)
                made_folders.add(path.parent)
            try:
                os.link(pooled[key], path)
            except OSError:  # no hard links here: a copy
                path.write_bytes(pooled[key].read_bytes())
    return len(pooled)


def build(shared_data: Path, data: Path, size=(64, 48), grain: float = 0.0, image=None) -> SimpleNamespace:
    """<data>/pitts30k in the original NetVLAD packaging: the 10,000 database and 6,816 query
    images under their real names (000/..., queries_real/...) with their real UTM positions in
    datasets/pitts30k_test.mat. One small generated image per distinct position, hard-linked
    to every name taken there (`size`, `grain`: see place_image; 640x480 with grain 8 makes
    JPEGs of about 86 KB; `image(easting, northing)` -> RGB uint8 array replaces place_image).
    `data` becomes the data root (it holds pitts30k/)."""
    from scipy.io import savemat

    base = shared_data / "ground-truth" / "patchnetvlad"
    gt = np.load(base / "pitts30k_test.npz")
    strip = lambda text: [n.removeprefix("./Pittsburgh250k/") for n in text.split()]  # noqa: E731
    db_names = strip((base / "pitts30k_imageNames_index.txt").read_text())
    q_names = strip((base / "pitts30k_imageNames_query.txt").read_text())
    root = data / "pitts30k"
    link_images(root, data / "pool", [(db_names, gt["utmDb"]), (q_names, gt["utmQ"])],
                image or (lambda easting, northing: place_image(easting, northing, size, grain)))
    (root / "datasets").mkdir()
    struct = {"whichSet": "test", "dbImageFns": np.array(db_names, dtype=object).reshape(-1, 1), "utmDb": gt["utmDb"].T,
              "qImageFns": np.array(q_names, dtype=object).reshape(-1, 1), "utmQ": gt["utmQ"].T,
              "numImages": 10000, "numQueries": 6816, "posDistThr": 25, "posDistSqThr": 625, "nonTrivPosDistSqThr": 100}
    savemat(root / "datasets" / "pitts30k_test.mat", {"dbStruct": struct})
    return SimpleNamespace(data=data, root=root, db_names=db_names, q_names=q_names, utm_db=gt["utmDb"], utm_q=gt["utmQ"])


def oracle_places(tree) -> dict:
    """Image name -> index of the database image nearest to where it was taken (for the oracle)."""
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(tree.utm_db).query(tree.utm_q)
    places = {name: i for i, name in enumerate(tree.db_names)}
    places.update({name: int(j) for name, j in zip(tree.q_names, nearest)})
    return places


if __name__ == "__main__":
    tree = build(Path(sys.argv[1]), Path(sys.argv[2]))
    print(f"{tree.root}: {len(tree.db_names)} database and {len(tree.q_names)} query images")
