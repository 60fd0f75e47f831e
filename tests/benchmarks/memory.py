"""Peak-memory figures of a benchmark process, from the kernel's own counters (Linux)."""


def rss_kb(field: str) -> int:
    """A field of /proc/self/status in kB: "VmRSS:" (now) or "VmHWM:" (peak since the last reset)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")


def measured(run) -> tuple[object, float, int, int]:
    """(what `run()` returns, its seconds, RSS in kB when it started, peak RSS in kB while it ran):
    the peak counter (VmHWM) is reset to the current RSS just before."""
    import time

    with open("/proc/self/clear_refs", "w") as refs:
        refs.write("5")
    base = rss_kb("VmRSS:")
    start = time.perf_counter()
    found = run()
    return found, time.perf_counter() - start, base, rss_kb("VmHWM:")
