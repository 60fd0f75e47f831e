"""The row-source contract (row_sources.py) where a mutation audit found it unpinned: reads are fresh
float32 whatever is stored, lent rows are read-only, memory sizes in decimal kB and never zero, and a
source returning the wrong block is named."""
import numpy as np
import pytest

from vprbench.errors import VPRBenchError
from vprbench.row_sources import ArrayRows, chunks, parse_memory, read_bytes_per_row


def test_reads_of_a_float16_array_are_float32_at_any_rows():
    stored = (np.arange(12, dtype=np.float32).reshape(4, 3) / 3).astype(np.float16)
    rows = ArrayRows(stored)
    picked = rows.read_rows_at(np.array([0, 2]))
    assert picked.dtype == np.float32 and np.array_equal(picked, stored[[0, 2]].astype(np.float32))
    assert read_bytes_per_row(rows) == 3 * (4 + 2)  # the float32 result and the float16 buffer it widens


def test_lent_rows_are_read_only_and_only_from_a_c_ordered_float32_array():
    array = np.ones((4, 3), np.float32)
    view = ArrayRows(array).view_rows(1, 3)
    with pytest.raises(ValueError):
        view[0, 0] = 5.0
    assert array[1, 0] == 1.0
    assert ArrayRows(np.asfortranarray(np.ones((4, 3), np.float32))).view_rows(0, 2) is None


@pytest.mark.parametrize("text, value", [("1KB", 1000), ("2KiB", 2048), ("3MB", 3 * 10**6)])
def test_memory_sizes_in_decimal_and_binary_units(text, value):
    assert parse_memory(text) == value


@pytest.mark.parametrize("text", ["0", "0GB", 0])
def test_a_memory_size_of_zero_is_refused(text):
    with pytest.raises(VPRBenchError, match="Memory size must be positive"):
        parse_memory(text)


def test_a_source_returning_the_wrong_block_is_named():
    class Short(ArrayRows):
        def read_rows(self, start, stop):
            return super().read_rows(start, stop)[:-1]

    with pytest.raises(VPRBenchError, match=r"returned shape \(1, 3\) for rows 0:2; expected \(2, 3\)"):
        list(chunks(Short(np.ones((4, 3), np.float32)), 2))


@pytest.mark.parametrize("dtype", [np.float32, np.float16])
def test_rows_read_at_indices_cost_what_read_bytes_per_row_says(dtype):
    """A float32 array's rows were copied twice (the fancy index, then np.array): an approximate index's
    training sample took twice the memory its search budgets."""
    from traced import peak_of

    rows = ArrayRows(np.ones((4000, 256), dtype))
    indices = np.arange(0, 4000, 2)
    picked, peak = peak_of(lambda: rows.read_rows_at(indices))
    assert picked.shape == (2000, 256) and peak < 1.05 * len(indices) * read_bytes_per_row(rows), peak
