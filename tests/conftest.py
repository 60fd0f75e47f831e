import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

#: real public data shared beside the repo (../shared/data, or $VPRBENCH_SHARED_DATA); never copied into it
SHARED_DATA = Path(os.environ.get("VPRBENCH_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data folder {SHARED_DATA} is absent (it sits beside the repo as ../shared/data)")
    return SHARED_DATA


@pytest.fixture(scope="session")
def example_plugin_site(tmp_path_factory) -> Path:
    """docs/examples/vprbench-example-plugin installed, as a separate package, into its own folder."""
    import subprocess
    import sys

    example = Path(__file__).resolve().parents[1] / "docs" / "examples" / "vprbench-example-plugin"
    target = tmp_path_factory.mktemp("site")
    subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--no-build-isolation",
                    "--no-index", "--target", str(target), str(example)], check=True)
    return target


@pytest.fixture(autouse=True)
def isolated_cache(tmp_path, monkeypatch):
    """Every test writes stores, vocabularies and results under its own temporary folder."""
    monkeypatch.setenv("VPRBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("VPRBENCH_DATA", raising=False)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch-home"))


def pytest_collection_modifyitems(config, items):
    """Benchmarks (tests/benchmarks) run only when asked: pytest tests/benchmarks --benchmark-enable."""
    if config.getoption("benchmark_enable", False):
        return
    skip = pytest.mark.skip(reason="benchmark: run with --benchmark-enable")
    for item in items:
        if "benchmarks" in item.path.parts:
            item.add_marker(skip)


# ---------------------------------------------------------------- a full-size Pitts-30k test tree
def place_image(easting: float, northing: float) -> np.ndarray:
    """64x48 RGB gratings whose phases and angles drift with position (nearby places look alike)."""
    y, x = np.mgrid[0:48, 0:64] / 48.0
    angle = (easting + northing) / 400.0
    a = np.sin(2 * np.pi * (3 * (x * np.cos(angle) + y * np.sin(angle)) + easting / 150.0))
    b = np.sin(2 * np.pi * (2 * (x * np.sin(angle) - y * np.cos(angle)) + northing / 170.0))
    grey = 127 + 60 * a + 50 * b
    return np.stack([grey, np.roll(grey, 7, axis=1), 255 - grey], axis=-1).clip(0, 255).astype(np.uint8)


@pytest.fixture(scope="session")
def pitts30k_tree(tmp_path_factory, shared_data) -> SimpleNamespace:
    """<data>/pitts30k in the original NetVLAD packaging: the 10,000 database and 6,816 query
    images under their real names (000/..., queries_real/...) with their real UTM positions in
    datasets/pitts30k_test.mat. One small generated image per distinct position, hard-linked
    to every name taken there."""
    from scipy.io import savemat

    base = shared_data / "ground-truth" / "patchnetvlad"
    gt = np.load(base / "pitts30k_test.npz")
    strip = lambda text: [n.removeprefix("./Pittsburgh250k/") for n in text.split()]  # noqa: E731
    db_names = strip((base / "pitts30k_imageNames_index.txt").read_text())
    q_names = strip((base / "pitts30k_imageNames_query.txt").read_text())
    data = tmp_path_factory.mktemp("data")
    root = data / "pitts30k"
    pool = data / "pool"
    pool.mkdir()
    made_folders, pooled = set(), {}
    for names, utm in ((db_names, gt["utmDb"]), (q_names, gt["utmQ"])):
        for name, (easting, northing) in zip(names, utm):
            key = (float(easting), float(northing))
            if key not in pooled:
                pooled[key] = pool / f"{len(pooled)}.jpg"
                Image.fromarray(place_image(*key)).save(pooled[key], quality=90)
            path = root / name
            if path.parent not in made_folders:
                path.parent.mkdir(parents=True, exist_ok=True)
                made_folders.add(path.parent)
            try:
                os.link(pooled[key], path)
            except OSError:  # no hard links here: a copy
                path.write_bytes(pooled[key].read_bytes())
    (root / "datasets").mkdir()
    struct = {"whichSet": "test", "dbImageFns": np.array(db_names, dtype=object).reshape(-1, 1), "utmDb": gt["utmDb"].T,
              "qImageFns": np.array(q_names, dtype=object).reshape(-1, 1), "utmQ": gt["utmQ"].T,
              "numImages": 10000, "numQueries": 6816, "posDistThr": 25, "posDistSqThr": 625, "nonTrivPosDistSqThr": 100}
    savemat(root / "datasets" / "pitts30k_test.mat", {"dbStruct": struct})
    return SimpleNamespace(data=data, root=root, db_names=db_names, q_names=q_names, utm_db=gt["utmDb"], utm_q=gt["utmQ"])


@pytest.fixture(scope="session")
def pitts30k_places(pitts30k_tree) -> dict:
    """Image name -> index of the database image nearest to where it was taken (for the oracle)."""
    from scipy.spatial import cKDTree

    tree = pitts30k_tree
    _, nearest = cKDTree(tree.utm_db).query(tree.utm_q)
    places = {name: i for i, name in enumerate(tree.db_names)}
    places.update({name: int(j) for name, j in zip(tree.q_names, nearest)})
    return places
