"""What search refuses or sets apart in the rows it is given: a row holding NaN or infinity
(refused, named), an all-zero row (an image with nothing described: it matches nothing), products
beyond float32's range, and a database and queries that cannot be compared."""
from __future__ import annotations

import numpy as np

from ..errors import VPRBenchError
from ..row_sources import ZERO_LENGTH, RowSource
from .chunks import Chunk

#: a row whose squared length is below this is all zero: an image with nothing described, which matches
#: nothing (row_sources.ZERO_LENGTH); its query counts as a failure at every K (AllZero)
ZERO_SQUARED = np.float32(ZERO_LENGTH) ** 2


def finite(block: np.ndarray) -> bool:
    """Whether every value is finite, by one float64 sum (of float32 values it cannot overflow)."""
    with np.errstate(invalid="ignore"):  # inf - inf
        return bool(np.isfinite(np.add.reduce(block, axis=None, dtype=np.float64)))


def check_finite(block: np.ndarray, what: str, start: int = 0, numbers=None) -> None:
    """Rows of `what` ("Query", "Database"), numbered from `start` (or by `numbers`), must be finite
    numbers: a NaN row would be ranked last (a NaN query given index -1), an infinite one first."""
    if not finite(block):
        bad = np.flatnonzero(~np.isfinite(block).all(axis=1))[0]
        row = start + bad if numbers is None else numbers[bad]
        raise VPRBenchError(f"{what} row {row} holds NaN or infinity, which search cannot rank: fix the "
                            "method or post-processor that made it (or describe again if its store was damaged).")


def zero_rows(block: np.ndarray, what: str, start: int = 0) -> np.ndarray:
    """(rows,) bool: which rows are all zero (`ZERO_SQUARED`), once every row is known finite; one pass
    over the rows (a squared length that is not finite sends the block to `check_finite`, which names
    a row holding NaN or infinity; a finite row too long to square is no zero row)."""
    with np.errstate(over="ignore", invalid="ignore"):
        squares = np.einsum("ij,ij->i", block, block)
    if not np.isfinite(squares).all():
        check_finite(block, what, start)
    return squares < ZERO_SQUARED


def checked(chunk: Chunk, what: str) -> np.ndarray:
    """The numbers of the chunk's all-zero rows, once each of its rows is known finite (`zero_rows`:
    little beside the products every row takes part in)."""
    found, start = [], chunk.start
    for tile, real in zip(chunk.tiles, chunk.real):
        found.append(start + np.flatnonzero(zero_rows(tile[:real], what, start)))
        start += real
    return np.concatenate(found)


def check_products(distances: np.ndarray) -> None:
    """Finite rows whose products overflowed float32 in grid units (rows far from unit length)."""
    if not np.isfinite(distances).all():
        raise VPRBenchError("Inner products of the descriptors exceed float32's range: they are too long to compare; "
                            "L2-normalise them.")


def check_pair(database: RowSource, queries: RowSource, k: int) -> None:
    if database.dim != queries.dim:
        raise VPRBenchError(f"Database descriptors have {database.dim} dims, queries {queries.dim}")
    if queries.row_count < 1:
        raise VPRBenchError("There are no query descriptors to search with.")
    if not 1 <= int(k) <= database.row_count:
        raise VPRBenchError(f"K = {k} must be between 1 and the {database.row_count} database rows; use a smaller --k.")
