"""Which stored record answers a run: found by the spec's identity (its protocol and row folder), then
kept only while what the spec does not name is the same (the dataset's bytes, the method's and each
stage's code, an approximate search's options and version), its metrics proven from its arrays."""
from __future__ import annotations

import warnings

from ..errors import VPRBenchError, require
from ..fsutil import warn_once
from ..text import shortened
from .results import check_layout, migrate_legacy, oldest_first, records_in, results_dir, run_folder


def find_result(spec, cache_dir=None, dataset_fingerprint: str | None = None,
                method_fingerprint: dict | None = None, accept=None) -> dict | None:
    """The newest stored record that answers `spec` (same row, same protocol, every K asked, what it
    named in the cache of the same content: `RunSpec.found`), its
    metrics recomputed from its per-query arrays (evaluation.proof), or None. A record whose arrays
    are missing or damaged, or that holds another row or protocol than its folder (copied there), answers
    nothing (named in a warning): its cell is evaluated again.
    With `dataset_fingerprint` (`Dataset.fingerprint`), only a record computed on that content
    answers: a benchmark's protocol names its splits and radius, not the bytes of a copy. With
    `method_fingerprint` (`store.method_fingerprint` of the method now), only a record whose
    descriptors were keyed by it answers: the spec names a method's options, not its code. With
    `accept` (a function of a record), only a record it accepts answers (a sweep's: the post-processing
    the run would fit). A record answers only while each stage's fingerprint is the one it was made with."""
    from ..spec import RunSpec
    from .proof import proven

    require(spec, RunSpec, "find_result(spec) takes a RunSpec (vprbench.spec.resolve_spec or spec_for)")
    for what, value, kind, example in (("dataset", dataset_fingerprint, str, "Dataset.fingerprint()"),
                                       ("method", method_fingerprint, dict, "store.method_fingerprint")):
        require(value, (kind, type(None)), f"find_result's {what}_fingerprint takes {example}, or None")  # else no match
    migrate_legacy(cache_dir)
    check_layout(results_dir(cache_dir))
    wanted, stages = {str(k) for k in spec.ks}, _created_stages(spec)
    fingerprints = None if stages is None else _stage_fingerprints(stages)
    # row and protocol as the record says, not as the folder it lies in is named (a file copied there)
    found = [r for r in records_in(run_folder(spec.dataset.protocol_hash, spec.row_key, cache_dir))
             if _in_place(r, spec)
             and wanted <= set(r["recall"]) and (r.get("spec") or {}).get("found", {}) == spec.found
             and dataset_fingerprint in (None, r.get("dataset_fingerprint")) and _same_search(r, spec, stages)
             and method_fingerprint in (None, r.get("method_fingerprint")) and _same_stages(r, fingerprints)
             and (accept is None or accept(r))]
    for record in reversed(oldest_first(found)):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            checked = proven(record)
        if not isinstance(checked, str):
            for warning in caught:  # stored metrics that disagree with the arrays
                warnings.warn(str(warning.message), stacklevel=2)
            return checked
        # the reason holds what the arrays' own warning said: one line, not two
        warnings.warn(f"{record.get('_source')} does not count as a result: {checked}", stacklevel=2)
    return None


def _in_place(record: dict, spec) -> bool:
    """Whether the record is a run of the row and protocol its folder is named after; one that is not
    (copied or moved there) answers nothing, said in a warning: its cell is evaluated again."""
    theirs, ours = (record["protocol"]["hash"], record["row_key"]), (spec.dataset.protocol_hash, spec.row_key)
    if theirs != ours:  # once per command, not once per cell of its row
        warn_once(record["_source"], f"{record['_source']} does not count as a result: it lies among the runs of "
                  f"protocol {ours[0]}, row {ours[1]}, but holds a run of protocol {shortened(theirs[0])}, row "
                  f"{shortened(theirs[1])} (copied or moved there; nothing was deleted).", stacklevel=3)
    return theirs == ours


def _created_stages(spec) -> list | None:
    """The spec's stages as they are here; None when one cannot be made here (its run says why)."""
    from ..stages.run import create_stages

    try:
        return create_stages(spec)
    except Exception:  # noqa: BLE001 - a plugin's stage may raise anything
        return None


def _same_search(record: dict, spec, stages: list | None) -> bool:
    """An approximate search's unset shortlist and ef_search follow the largest K: a record made with
    another largest K searched with another shortlist, so its Recall@1 is not this spec's. A record made
    by another version of the index's code (`approximate.VERSIONS`) is not this spec's either."""
    if not spec.search.approximate:
        return True
    if stages is None:  # a stage that cannot be made here: its depth is unknown
        return False
    from ..search.approximate import VERSIONS, index_options
    from ..stages.run import retrieval_depth

    found = record.get("search") or {}
    if found.get("version", 1) != VERSIONS[spec.search.index]:
        return False
    try:
        database = int(record["counts"]["database"])
        depth = retrieval_depth(stages, spec.ks, database, spec.dataset.name)
        wanted = index_options(spec.search.index, database, int(found["dim"]), depth, spec.search.options)
    except (VPRBenchError, KeyError, TypeError, ValueError):
        return False
    return found.get("options") == wanted


def _stage_fingerprints(stages: list) -> list[dict] | None:
    """Each stage's fingerprint now (`Stage.fingerprint`, a version its author raises), or None when
    one cannot be told (its run says why)."""
    from ..stages.run import stage_fingerprint

    try:
        return [stage_fingerprint(stage) for stage in stages]
    except Exception:  # noqa: BLE001 - a plugin's fingerprint may raise anything
        return None


def _same_stages(record: dict, now: list[dict] | None) -> bool:
    """The record was made with each stage's fingerprint as it is now: the spec names a stage's options,
    not its code. A record without one (written before stages had one) was made with the default, {}."""
    if now is None:
        return False
    made = [s.get("fingerprint") or {} for s in record.get("stages") or [] if isinstance(s, dict)]
    return made + [{}] * (len(now) - len(made)) == now
