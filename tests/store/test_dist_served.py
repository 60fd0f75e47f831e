"""A torchrun whose stores are already complete still records one entry per rank."""

from vprbench.datasets import load_dataset
from vprbench.distributed import Ranks
from vprbench.evaluation.extract import describe_splits

import vprbench


class RankZeroOfTwo(Ranks):
    """Rank 0 of a 2-rank job in one process: the collectives see rank 1 holding the same."""

    def __init__(self):
        super().__init__(rank=0, world_size=2)

    def all_gather(self, value) -> list:
        return [value, value]

    def broadcast(self, value):
        return value


def test_served_stores_record_one_entry_per_rank(shared_data, tmp_path):
    dataset = load_dataset("corridor", shared_data)
    splits = {"database": dataset.database[:20], "queries": dataset.queries[:10]}
    method = vprbench.create_method("thumb-test")
    first = describe_splits(method, splits, root=dataset.root, label="corridor", cache_dir=tmp_path)
    assert first.computed == {"database": 20, "queries": 10} and first.per_rank == [first.computed]
    served = describe_splits(method, splits, root=dataset.root, label="corridor", cache_dir=tmp_path,
                             ranks=RankZeroOfTwo())
    assert served.stores is not None and served.computed == {"database": 0, "queries": 0}
    assert served.per_rank == [{"database": 0, "queries": 0}, {"database": 0, "queries": 0}]
