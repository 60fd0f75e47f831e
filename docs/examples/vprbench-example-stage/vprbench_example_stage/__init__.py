"""A third-party re-ranker: a candidate's score is its similarity to the query plus its mean
similarity to the query's first `n` candidates (neighbourhood consensus)."""
import numpy as np
from pydantic import Field

from vprbench.stages import Candidates, RerankOptions, Stage, register_stage


class ConsensusOptions(RerankOptions):
    n: int = Field(3, ge=1)
    weight: float = 1.0


class Consensus(Stage):
    track = "re-ranked"
    Options = ConsensusOptions
    description = "similarity to the query + weight x mean similarity to its first n candidates"

    def apply(self, candidates, context):
        scores = np.empty(candidates.indices.shape, dtype=np.float64)
        for q in range(candidates.query_count):
            order = np.argsort(candidates.indices[q])
            rows = np.empty((candidates.k, context.database.dim), np.float32)
            rows[order] = context.database.read_rows_at(candidates.indices[q][order])
            query = context.queries.read_rows(q, q + 1)[0]
            consensus = (rows @ rows[: self.options.n].T).mean(axis=1)
            scores[q] = rows @ query + self.options.weight * consensus
        ranked = np.argsort(-scores, axis=1, kind="stable")
        return Candidates(np.take_along_axis(candidates.indices, ranked, 1),
                          np.take_along_axis(scores, ranked, 1).astype(np.float32))


def register():
    register_stage("consensus", "vprbench_example_stage:Consensus")
