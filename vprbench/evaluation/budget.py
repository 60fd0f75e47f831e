"""The run's memory plan: the least budget of every part (retrieval's search, each stage) from the
shapes of the rows they read, checked once before any of them runs.

Each part still checks its own budget when it starts (a caller may run it alone); this only makes
a run that is bound to be refused by one of them say so at once, naming the largest need, rather
than run the search and refuse in a stage, one number at a time.
"""
from __future__ import annotations

from numbers import Integral

from ..errors import VPRBenchError
from ..row_sources import format_budget, format_bytes


def retrieval_need(compare: str, database, queries, k: int, index: str = "exact", options: dict | None = None) -> int:
    """The least budget retrieval's search of these rows (post-processed, as the search reads them) takes."""
    if compare != "cosine":  # a distance: the sequence search with sequences of one frame (retrieve.compared_search)
        from ..stages.sequence.search import sequence_need

        return sequence_need(database, queries, k, score="diagonal", length=1)
    if index == "exact":
        from ..search.exact import search_need

        return search_need(database, queries, k)
    from ..search.approximate import approximate_need

    return approximate_need(database, queries, k, index, options)


def stage_needs(stages, database, queries, depth: int) -> list[tuple[str, int]]:
    """(part, bytes) of each stage that says its least budget, each handed the candidates it would be
    (its `candidates_needed`, else as many as the stage before it kept)."""
    from ..stages.run import in_stage

    found, k = [], depth
    for stage in stages:
        with in_stage(stage, "candidates_needed"):
            k = stage.candidates_needed() or k
        with in_stage(stage, "least_budget"):
            need = stage.least_budget(database, queries, k)
        if need is not None:
            found.append((f"stage {stage.name!r}", said_number(need, f"Stage {stage.name!r}: least_budget()", "stage",
                                                               or_none=True)))
    return found


def said_number(found, hook: str, kind: str, least: int = 0, or_none: bool = False) -> int:
    """`found`, what a plugin's `hook` returned for a size, as an int >= `least` (compared with the budget as a
    number), or refused in one line naming the hook."""
    if isinstance(found, bool) or not isinstance(found, Integral) or found < least:
        raise VPRBenchError(f"{hook} returned {found!r}, not a whole number >= {least}{' or None' if or_none else ''}; "
                            f"fix the {kind}.")
    return int(found)


def check_run_budget(parts: list[tuple[str, int]], budget: int) -> None:
    """Refuse, once, a budget below the largest of `parts`' needs ((part, bytes)), naming that part."""
    if not parts:
        return
    part, need = max(parts, key=lambda found: found[1])  # the first of equal needs
    if budget < need:
        each = ", ".join(f"{name} {format_budget(bytes_)}" for name, bytes_ in parts)
        raise VPRBenchError(f"A memory budget of {format_bytes(budget)} is too small for this run: {part} needs the "
                            f"most ({each}). Raise --search-memory (memory_budget) to at least {format_budget(need)}.")
