"""Search tests run on one thread, some on tiles of 1,024 rows or with torch's thread count changed."""
import pytest

from vprbench.search.exact import tile_rows


@pytest.fixture(autouse=True)
def one_thread():
    """BLAS and OpenMP on one thread: results do not depend on it, and on a shared 2-core
    machine two contending threads made these tests three times slower."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


@pytest.fixture
def tiles_of_1024(monkeypatch):
    """Tiles of 1,024 rows (at these small dimensions the grid has 4,096), so that a few
    thousand rows cross several tile and chunk borders."""
    import vprbench.search.exact as search_module

    assert tile_rows(8) == tile_rows(1024) == 4096 and tile_rows(35_721) == 1792 and tile_rows(49_152) == 1280
    monkeypatch.setattr(search_module, "tile_rows", lambda dim: 1024)



@pytest.fixture
def torch_threads():
    import torch

    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)

