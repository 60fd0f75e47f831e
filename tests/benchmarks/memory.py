"""Peak-memory figures of a benchmark process, from the kernel's own counters (Linux)."""


def rss_kb(field: str) -> int:
    """A field of /proc/self/status in kB: "VmRSS:" (now) or "VmHWM:" (peak since the last reset)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field):
                return int(line.split()[1])
    raise RuntimeError(f"{field} not in /proc/self/status")
