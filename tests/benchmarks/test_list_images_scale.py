"""Opt-in benchmark: listing the largest folder of images vprbench walks, Pitts-250k's 254,064 database
images (a map vocabulary fitted on a folder; the utm-names layout lists Pitts-250k test's 83,952 the same
way), reached through linked folders, as list_images follows them since 2026-12-07.

    pytest tests/benchmarks/test_list_images_scale.py --benchmark-enable -s

The images are empty files named as Pitts-250k's (listing opens none): 11 folders 000..010 of up to
24,000, each a symbolic link to where the files are, beside macOS's hidden '._' copies and a hidden folder.
"""
import json
import os

import pytest

from memory import measured
from vprbench.images import list_images

IMAGES, PER_FOLDER = 254_064, 24_000


@pytest.fixture(scope="module")
def linked_tree(tmp_path_factory):
    root = tmp_path_factory.mktemp("pitts250k-database")
    real, listed = root / "real", root / "database"
    listed.mkdir()
    names = []
    for i in range(IMAGES):
        folder = f"{i // PER_FOLDER:03d}"
        if i % PER_FOLDER == 0:
            (real / folder).mkdir(parents=True)
            os.symlink(real / folder, listed / folder)
            open(real / folder / f"._{i:06d}_pitch1_yaw1.jpg", "wb").close()  # hidden: no image
        name = f"{folder}/{i:06d}_pitch{i % 2 + 1}_yaw{i % 12 + 1}.jpg"
        open(real / name, "wb").close()
        names.append(name)
    (listed / ".thumbnails").mkdir()  # hidden folder: not walked
    open(listed / ".thumbnails" / "a.jpg", "wb").close()
    return listed, names


def test_list_images_through_linked_folders_at_pitts250k_size(linked_tree, monkeypatch, benchmark):
    listed, names = linked_tree
    calls = {"stat": 0, "lstat": 0}
    for name in calls:  # counted: a check per image against every folder (or image) would show here
        real = getattr(os, name)
        monkeypatch.setattr(os, name, lambda *a, _real=real, _name=name, **k: calls.__setitem__(_name, calls[_name] + 1)
                            or _real(*a, **k))
    runs = []
    benchmark.pedantic(lambda: runs.append(measured(lambda: list_images(listed, recursive=True, natural=True))),
                       rounds=1, iterations=1)
    found, seconds, base_kb, peak_kb = runs[0]
    assert [p.relative_to(listed).as_posix() for p in found] == names  # natural order of the names, links kept
    per_image = {name: count / IMAGES for name, count in calls.items()}
    # two per image (is it a link? a regular file?) and a few per folder: linear
    assert per_image["stat"] + per_image["lstat"] < 2.01, per_image
    extra_mb = (peak_kb - base_kb) / 1024
    # a Path and its natural-order key is about 0.8 KB an image (211 MB measured); 2 KB an image allows for
    # another Python, not for a copy of each image's bytes or for the listing held twice over
    assert extra_mb < 2 * IMAGES / 1024, extra_mb
    figures = {"images": len(found), "seconds": round(seconds, 2), "peak_extra_mb": round(extra_mb),
               "calls_per_image": per_image}
    benchmark.extra_info.update(figures)
    print("\n" + json.dumps(figures))
