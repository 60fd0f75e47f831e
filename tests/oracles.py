"""Perfect inputs for a re-ranker's oracle test: queries that are database images themselves (in other formats),
handed over with the true match last; a re-ranker that works puts each first (R@1 = 100), re-ordering only."""
from __future__ import annotations

import numpy as np
from PIL import Image

from vprbench.stages import Candidates

#: Corridor database rows far enough apart to be different places
PLACES = (0, 20, 40, 60, 80, 100)


class Images:
    """The little a re-ranker reads of a dataset: image paths per split, a name and a content key per split."""

    def __init__(self, database, queries):
        self.name, self.database, self.queries = "oracle", list(database), list(queries)

    def images_fingerprint(self, cache_dir=None):
        return {"database": "|".join(map(str, self.database)), "queries": "|".join(map(str, self.queries))}


def variants(corridor, folder):
    """The database images of PLACES, each written as a query in another format or size (perfect inputs)."""
    written = []
    for i, row in enumerate(PLACES):
        image, path = Image.open(corridor.database[row]).convert("RGB"), folder / f"query{i}.png"
        kind = i % 5
        if kind == 1:
            image = image.convert("L")
        elif kind == 2:
            image = image.convert("RGBA")
        elif kind == 3:
            image = Image.fromarray(np.asarray(image.convert("L")).astype(np.uint16) * 257)  # 16-bit grey
        elif kind == 4:
            image = image.resize((image.width * 2, image.height * 2), Image.BICUBIC)
        image.save(path)
        written.append(path)
    return written


def worst_first(count):
    """Per query, every database image with the true match (its own index) last, scores descending."""
    indices = np.array([np.roll(np.arange(count), -(q + 1)) for q in range(count)], dtype=np.int64)
    return Candidates(indices, np.tile(np.linspace(1, 0, count, dtype=np.float32), (count, 1)))


def assert_oracle(given: Candidates, found: Candidates):
    assert found.indices[:, 0].tolist() == list(range(given.query_count))  # R@1 = 100
    assert (np.sort(found.indices, 1) == np.sort(given.indices, 1)).all()  # re-ordered, nothing dropped or added
