"""What a call allocates at its peak, as numpy and Python report it to tracemalloc (memory-budget tests)."""
import tracemalloc


def peak_of(call):
    """(call(), the most bytes it held at once): allocations traced from its start to its end."""
    tracemalloc.start()
    try:
        result = call()
        return result, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
