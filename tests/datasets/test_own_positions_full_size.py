"""positions.csv of a folder of one's own at the size of the largest dataset vprbench serves: Pitts-250k
as a folder (254,064 database and 8,280 query images; one row each). Rows are matched to image names
and never opened, so the images need not exist: the paths are made up, as the folder's listing gives them."""
import os
import time
import warnings

import numpy as np
import pytest

from vprbench.datasets.layouts.own_data import positions_from_csv
from vprbench.errors import VPRBenchError

DATABASE, QUERIES = 254_064, 8_280


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("pitts250k-own")
    names = [f"database/{i:06d}.jpg" for i in range(DATABASE)] + [f"queries/{i:06d}.jpg" for i in range(QUERIES)]
    xy = np.random.default_rng(0).uniform(0, 7000, (len(names), 2)).round(2)  # a city of 7 x 7 km, as Pittsburgh
    rows = "\n".join(f"{name},{x},{y}" for name, (x, y) in zip(names, xy))
    (root / "positions.csv").write_text(f"image,x,y\n{rows}\n")
    return root, [root / name for name in names], xy


def test_every_row_matched_at_pitts250k_size(folder, monkeypatch):
    root, images, xy = folder
    looked = []  # a file looked for per row (only rows naming no image listed are): none here
    monkeypatch.setattr(os.path, "isfile", lambda path, _real=os.path.isfile: looked.append(path) or _real(path))
    started = time.perf_counter()
    positions, unit = positions_from_csv(root / "positions.csv", root, images[::-1])  # matched by name, not order
    took = time.perf_counter() - started
    assert [p for p in looked if str(root) in str(p)] == []
    assert unit == "metres" and positions.shape == (DATABASE + QUERIES, 2)
    np.testing.assert_array_equal(positions, xy[::-1])
    # generous: 2.5 s on 2 shared cores; matching each image to its row by scanning the rows (quadratic)
    # would take hours at 262,344 rows
    assert took < 60, took


def test_a_bad_value_in_a_long_file_is_one_line(folder, tmp_path):
    """pandas reads a long file in chunks: a column holding text in its last chunk only was a DtypeWarning
    (pointing into vprbench, 'specify dtype option on import') before the refusal, at this size only."""
    root, images, _ = folder
    text = (root / "positions.csv").read_text().splitlines()
    text[-1] = text[-1].rsplit(",", 2)[0] + ",12;5 m,4"  # a typo in the last query's row
    (tmp_path / "positions.csv").write_text("\n".join(text) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning before the refusal
        with pytest.raises(VPRBenchError) as caught:
            positions_from_csv(tmp_path / "positions.csv", root, images)
    said = str(caught.value)
    assert "\n" not in said and "non-numeric positions in 1 row(s), e.g. for ['queries/008279.jpg']" in said, said
