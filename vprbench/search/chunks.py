"""The rows exact search computes on: tiles of a fixed grid, read a chunk at a time.

Tiles are aligned to row 0, their size a function of the dimension only, so a row's product
has a shape set by the data's size, never by the memory budget or by the row's place in a
read. A chunk is whole tiles (the last chunk may end with the source's short last tile).

A source that lends its rows (`view_rows`: a descriptor store's own file pages, an in-memory
float32 array) is computed on where it is: no copy and no fresh memory. New memory costs
its first touch, which on a virtual machine that backs memory lazily takes about as long as
the products themselves at Nordland's size (1 s per 256 MB). Other sources (float16 stores,
post-processed rows) are read into buffers.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..errors import VPRBenchError

#: a tile of rows is at most this large (and 256..4,096 rows, a multiple of 256): tiles this
#: big keep BLAS near its peak (a 1,024-row tile of 35,721 dims reaches 86 % of a whole product, 1,792 rows 90 %)
TILE_BYTES = 256 * 2**20
#: tiles are multiples of this many rows; a last tile shorter than this is padded with zero rows
#: to it: never the one-row or tiny products where BLAS switches kernels
TILE_STEP = 256


def tile_rows(dim: int) -> int:
    """Rows per tile of the grid scores are computed on; depends on the dimension only."""
    rows = TILE_BYTES // (4 * int(dim))
    return int(min(4096, max(TILE_STEP, rows // TILE_STEP * TILE_STEP)))


def product_rows(rows: int, tile: int) -> int:
    """Rows a tile holding `rows` rows is computed with: its own, or TILE_STEP (within the
    tile) when it has fewer (the rest zeros)."""
    return int(rows) if rows >= TILE_STEP else min(int(tile), TILE_STEP)


def read_into(rows, start: int, stop: int, out: np.ndarray) -> None:
    """Rows start:stop of a row source into `out` (float32, stop - start rows): straight into
    it when the source can (`read_rows_into`), else through a fresh array."""
    reader = getattr(rows, "read_rows_into", None)
    if reader is not None:
        reader(start, stop, out)
        return
    block = np.asarray(rows.read_rows(start, stop), dtype=np.float32)
    if block.shape != (stop - start, rows.dim):
        raise VPRBenchError(f"Row source returned shape {block.shape} for rows {start}:{stop}; expected "
                            f"({stop - start}, {rows.dim}).")
    out[...] = block


def lent(rows, start: int, stop: int) -> np.ndarray | None:
    """Rows start:stop as the source's own read-only float32 memory, or None when it has none."""
    view = getattr(rows, "view_rows", None)
    found = view(start, stop) if view is not None else None
    if found is not None and (found.shape != (stop - start, rows.dim) or found.dtype != np.float32):
        raise VPRBenchError(f"Row source lent shape {found.shape} ({found.dtype}) for rows {start}:{stop}; "
                            f"expected ({stop - start}, {rows.dim}) float32.")
    return found


class Chunk(NamedTuple):
    start: int                # first row
    count: int                # rows
    tiles: list[np.ndarray]   # the chunk's tiles in order, each ready for products (product_rows rows)
    real: list[int]           # rows of each tile that are the source's (the rest are zero padding)


def load(rows, start: int, count: int, tile: int, buffer) -> Chunk:
    """Rows start:start+count as tiles: where they are when the source lends them (a short last
    tile copied and padded), else read into `buffer()` (an array of at least the chunk's rows)."""
    real = [min(tile, count - t0) for t0 in range(0, count, tile)]
    view = lent(rows, start, start + count)
    if view is None:
        whole = buffer()
        read_into(rows, start, start + count, whole[:count])
    tiles = []
    for t0, n in zip(range(0, count, tile), real):
        held = product_rows(n, tile)
        if view is None:
            whole[t0 + n:t0 + held] = 0
            tiles.append(whole[t0:t0 + held])
        elif held == n:
            tiles.append(view[t0:t0 + n])
        else:  # fewer than TILE_STEP rows: at most TILE_STEP rows copied
            padded = np.zeros((held, rows.dim), dtype=np.float32)
            padded[:n] = view[t0:t0 + n]
            tiles.append(padded)
    return Chunk(start, count, tiles, real)


class ChunkReader:
    """A row source read chunk by chunk, `passes` times over, into at most `buffers` buffers
    (allocated only if the source does not lend its rows). The first chunk is read at once,
    beside the caller's own setup; with two buffers each next chunk is read in a thread
    while the caller computes on the current one. A source of no more chunks than buffers
    is read once and kept. A caller lets go of a chunk before it asks for the next, so that
    no more chunks are held than there are buffers, lent rows too."""

    def __init__(self, rows, chunk_rows: int, tile: int, passes: int, buffers: int = 2):
        from concurrent.futures import ThreadPoolExecutor

        self.rows, self.chunk_rows, self.tile = rows, int(chunk_rows), int(tile)
        self.starts = list(range(0, rows.row_count, self.chunk_rows))
        self.buffers = [None] * min(int(buffers), len(self.starts))
        kept = len(self.starts) <= len(self.buffers)
        self.kept = [] if kept else None  # the chunks, once read, when they are all kept
        self.reads = len(self.starts) * (1 if kept else int(passes))  # in order 0, 1, .., 0, 1, ..
        self.step = 0
        self.pool = ThreadPoolExecutor(1, thread_name_prefix="vprbench-read")
        self.next = self.pool.submit(self._fill, 0)

    def _buffer(self, step: int) -> np.ndarray:
        slot = step % len(self.buffers)  # not the one the caller computes on
        if self.buffers[slot] is None:
            held = -(-self.chunk_rows // self.tile) * self.tile
            self.buffers[slot] = np.empty((held, self.rows.dim), dtype=np.float32)
        return self.buffers[slot]

    def _fill(self, step: int) -> Chunk:
        start = self.starts[step % len(self.starts)]
        count = min(self.chunk_rows, self.rows.row_count - start)
        return load(self.rows, start, count, self.tile, lambda: self._buffer(step))

    def __iter__(self):
        """One pass over the source, a Chunk at a time."""
        for i in range(len(self.starts)):
            if self.step >= self.reads:  # every chunk kept, and read
                yield self.kept[i]
                continue
            if self.next is None:
                self.next = self.pool.submit(self._fill, self.step)
            chunk, self.next = self.next.result(), None
            self.step += 1
            if len(self.buffers) > 1 and self.step < self.reads:
                self.next = self.pool.submit(self._fill, self.step)
            if self.kept is not None:
                self.kept.append(chunk)
            yield chunk
            chunk = None  # let go (rows lent are unmapped once the caller lets go too)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
