"""Query expansion and database-side augmentation on the retriever's global descriptors.

alpha-QE (Radenovic et al., "Fine-tuning CNN image retrieval with no human annotation", TPAMI
2018): a query becomes the normalised sum of itself and its top `n` candidates, each weighted by
its similarity to the query raised to `alpha`. DBA does the same to every database image with
its own top `n` database neighbours. Both then re-score the top K with the new descriptors.
Rows are read a query at a time (or a block of database rows at a time): nothing is held whole.
"""
from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator

from ..errors import VPRBenchError
from ..row_sources import ArrayRows, format_budget, format_bytes, read_bytes_per_row
from ..search.exact import SCORE_TOLERANCE, exact_search, least_budget, most_that_fit
from .base import Candidates, RerankOptions, Stage, StageContext, progress_task, reordered


#: database images dba expands per search of the database (at most; less when the memory budget says so)
BLOCK_ROWS = 8192


class ExpansionOptions(RerankOptions):
    #: neighbours summed in (the candidate list's first n, or a database image's n nearest)
    n: int = Field(10, ge=1)
    alpha: float = Field(3.0, ge=0)


class AlphaQEOptions(ExpansionOptions):
    @model_validator(mode="after")
    def _n_within_k(self):
        # n beyond k would sum in the same k candidates: another label, the same computation
        if self.n > self.k:
            default = "" if "n" in self.model_fields_set else " (its default)"
            raise ValueError(f"n = {self.n}{default} sums in more candidates than the top k = {self.k} it re-ranks; "
                             f"give n <= {self.k}, or a larger k")
        return self


def _normalised(rows: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(rows, axis=-1, keepdims=True)
    return rows / np.maximum(norms, 1e-12)


def _dots(rows: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Each of `rows` times `row`, summed by numpy's own loop: the BLAS splits long rows' sums by its thread
    count (8,192 dims, 100 rows: 4 % of dba's float32 scores 2.5e-8 apart at 1 and 2 threads, a grid step
    where one lies at a boundary), and a run's spec names no thread count."""
    return np.einsum("ij,j->i", rows, row)


def _weighted(base: np.ndarray, neighbours: np.ndarray, alpha: float) -> np.ndarray:
    """base + sum of neighbours weighted by similarity^alpha, L2-normalised (one row). Similarities of unit
    rows are clipped to [0, 1]: one a rounding above 1 overflowed to inf under a large alpha."""
    weights = np.clip(_dots(neighbours, base), 0.0, 1.0).astype(np.float64) ** alpha  # alpha may not fit float32
    return _normalised(base + np.einsum("i,ij->j", weights, neighbours))  # no BLAS either (`_dots`)


def _rows_at(source, indices: np.ndarray) -> np.ndarray:
    """Rows of `source` in the order of `indices` (a row source reads sorted indices)."""
    unique, inverse = np.unique(indices, return_inverse=True)
    return source.read_rows_at(unique)[inverse]


def _augmenting(database, needed: int, n: int, rows: int) -> int:
    """Bytes dba holds augmenting `needed` database images, `rows` of them per search of their `n` nearest:
    the augmented rows, one row's neighbours, a block of rows read, and its search."""
    read = read_bytes_per_row(database)
    return needed * database.dim * 4 + n * read + rows * read + least_budget(database, rows, n)


class _Expansion(Stage):
    track = "re-ranked"
    Options = ExpansionOptions

    def fingerprint(self) -> dict:
        return {"version": 3}  # 2: weights in float64, similarities clipped to [0, 1]; 3: products without the BLAS

    def check_compare(self, compare: str) -> None:
        """Expansion weights and re-scores by inner products of unit rows: on a method compared by a distance
        (sad's mean absolute difference) they are neither its similarity nor its ranking, so refuse."""
        if compare != "cosine":
            raise VPRBenchError(f"Stage {self.name!r} expands descriptors compared by cosine (inner products of unit "
                                f"rows); the method's are compared by {compare!r}: use a method compared by cosine.")


class AlphaQE(_Expansion):
    description = "alpha query expansion: the query with its top n candidates, re-scoring the top K"
    Options = AlphaQEOptions

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        self.check_compare(context.compare)
        n, alpha = self.options.n, self.options.alpha
        scores = np.empty(candidates.indices.shape, dtype=np.float64)
        advance = progress_task(context, f"{self.name} re-ranking", candidates.query_count)
        for q in range(candidates.query_count):
            query = context.queries.read_rows(q, q + 1)[0]
            rows = _rows_at(context.database, candidates.indices[q])
            expanded = _weighted(query, rows[:n], alpha)
            scores[q] = _dots(rows, expanded)
            advance()
        return reordered(candidates.indices, scores, SCORE_TOLERANCE)


class DatabaseAugmentation(_Expansion):
    description = "database-side augmentation: each database image with its n nearest database images"

    def check(self, dataset) -> None:
        others = len(dataset.database) - 1  # n beyond them would sum in the same images under another label
        if self.options.n > others:
            raise VPRBenchError(f"Stage {self.name!r}: n = {self.options.n} nearest database images, but each database "
                                f"image of {dataset.name} has {others} others: give n <= {others}.")

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        self.check_compare(context.compare)
        n, alpha, database = self.options.n, self.options.alpha, context.database
        needed = np.unique(candidates.indices)
        n += 1  # an image is its own nearest neighbour
        block, search_budget = self._blocks(database, len(needed), n, context.memory_budget)
        augmented = np.empty((len(needed), database.dim), dtype=np.float32)
        advance = progress_task(context, f"{self.name} augmenting database images", len(needed))
        for start in range(0, len(needed), block):
            rows = database.read_rows_at(needed[start:start + block])
            found = exact_search(database, ArrayRows(rows), n, memory_budget=search_budget)
            for i, (row, neighbours) in enumerate(zip(rows, found.indices)):
                others = _rows_at(database, neighbours[neighbours != needed[start + i]][: n - 1])
                augmented[start + i] = _weighted(row, others, alpha)
            advance(len(rows))
        position = np.searchsorted(needed, candidates.indices)
        scores = np.empty(candidates.indices.shape, dtype=np.float64)
        for q in range(candidates.query_count):
            scores[q] = _dots(augmented[position[q]], context.queries.read_rows(q, q + 1)[0])
        return reordered(candidates.indices, scores, SCORE_TOLERANCE)

    def least_budget(self, database, queries, k: int) -> int:
        # which images it augments is known once retrieval has run; at least one query's k: what is sure to be
        # needed, so no budget the stage would take is refused (a larger need is refused by the stage then)
        needed = min(database.row_count, k)
        return _augmenting(database, needed, self.options.n + 1, 1)

    def _blocks(self, database, needed: int, n: int, budget: int) -> tuple[int, int]:
        """(database images augmented per search of the database, that search's budget): the budget holds
        the augmented rows until every query is scored, a block of rows with one row's n neighbours, and
        the search. Blocks of at most BLOCK_ROWS, so progress moves during an 84k-image database's expansion."""
        row, read = database.dim * 4, read_bytes_per_row(database)
        held = needed * row + n * read

        def least(rows: int) -> int:
            return _augmenting(database, needed, n, rows)

        block = max(1, min(needed, BLOCK_ROWS, (budget - held) // (8 * database.dim * (n + 1))))
        block = most_that_fit(block, least, budget)
        if least(block) > budget:
            raise VPRBenchError(
                f"Stage {self.name!r}: a memory budget of {format_bytes(budget)} is too small. It holds the {needed:,} "
                f"augmented database rows of {database.dim:,} dims ({format_bytes(needed * row)}) until every query "
                f"is scored, and a search of the database beside them: {format_bytes(least(block))} in all. Raise "
                f"--search-memory to at least {format_budget(least(block))}, or re-rank fewer candidates (--rerank-k) or "
                "descriptors of fewer dims.")
        return block, budget - held - block * read
