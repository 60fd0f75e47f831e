"""User-facing errors: the CLI prints their message and exits non-zero, without a traceback."""


class VPRBenchError(Exception):
    """A problem with the user's input or environment; the message says what and how to fix it."""


def closest_names(name: str, choices, n: int = 3) -> str:
    """' Did you mean: a, b?' for the names closest to `name`, or '' when none is close."""
    import difflib

    close = difflib.get_close_matches(name, list(choices), n=n, cutoff=0.5)
    return f" Did you mean: {', '.join(close)}?" if close else ""
