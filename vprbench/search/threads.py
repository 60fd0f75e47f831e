"""Where search products run: each on one thread of its own, alone or side by side with others.

A product on several threads may split its sums by their count (oneDNN in torch before 2.11, numpy's
BLAS), so its last bits, and a tie at the K-th place, would follow the machine's thread count. Exact
search and the sequence stage cut their work into fixed-shape products and run each on one thread.
"""
from __future__ import annotations


def blas_controller():
    """threadpoolctl's handle on the BLAS and OpenMP libraries this process loaded. Finding them reads the
    process's libraries (milliseconds): a search finds them once, then reads and limits their threads
    through it (found once per block of queries, they were most of a small-block search's time)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def search_threads(libraries=None) -> int:
    """Threads a search computes on: as many as the BLAS would use now (threadpoolctl sees its
    setting, e.g. OMP_NUM_THREADS or threadpool_limits); `libraries` from `blas_controller`. Of
    several BLAS libraries the most: OpenCV 4.8 ships one that keeps to one thread whatever it is
    told, and beside it (any run that imported cv2) every search ran on one thread."""
    found = [int(lib["num_threads"]) for lib in (libraries or blas_controller()).info() if lib.get("user_api") == "blas"]
    return max([1, *found])


def one_thread_each() -> None:
    """Each search thread computes alone: one OpenMP thread for faiss and oneDNN, set for this thread
    only (torch.set_num_threads would change every new thread's)."""
    import faiss
    import torch
    from threadpoolctl import threadpool_limits

    faiss.omp_set_num_threads(1)
    torch.get_num_threads()  # torch sets a thread's OpenMP count at its first call there: before ours
    threadpool_limits(1, user_api="openmp")


class ProductThreads:
    """`count` threads that each compute alone, side by side; for a count of one, the calling thread
    under a one-thread limit of every BLAS and OpenMP library. A context: the threads end with it."""

    def __init__(self, count: int, libraries=None, name: str = "vprbench-search"):
        self.libraries = libraries or blas_controller()
        self.pool = None
        if count > 1:
            from concurrent.futures import ThreadPoolExecutor

            self.pool = ThreadPoolExecutor(count, name, one_thread_each)

    def __enter__(self) -> ProductThreads:
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True)

    def run(self, product, work: list[tuple]) -> None:
        """product(*args) for every args in `work`, side by side when there are threads."""
        if self.pool is None:
            with self.libraries.limit(limits=1):
                for args in work:
                    product(*args)
            return
        # the BLAS limit is the process's: only while the products run (reading a chunk keeps its threads)
        with self.libraries.limit(limits=1, user_api="blas"):
            list(self.pool.map(product, *zip(*work)))
