"""The one entry point: `evaluate(spec)` runs every evaluation, top to bottom.

    load the dataset (its protocol)  ->  create the method  ->  describe both splits (stores)
    ->  retrieve (post-process, search)  ->  score  ->  the record

A single command, a matrix, a plan, `reproduce` and torchrun are loops over specs that call it.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from ..distributed import Ranks
from ..errors import VPRBenchError, require
from ..progress import phase
from ..registration import source_of
from ..row_sources import DEFAULT_MEMORY_BUDGET
from ..methods.attributes import restamp_fingerprint, set_attributes, use_dataset
from ..methods.objects import check_method
from ..methods.registry import checked_run_options
from ..search.approximate import searched_to, sized_options
from ..spec import RunSettings, RunSpec
from .budget import check_run_budget, retrieval_need, stage_needs
from .extract import describe_splits
from .identity import protocol_of
from .joint import describe_members, joint_members
from .metrics import ks_within_database
from .postprocess import check_database_size, check_joint_budget
from .record import result_record
from .retrieve import check_compare, retrieve
from ..stages.base import Candidates, StageContext
from ..stages.candidates import check_scores, images_identity, read_candidates, write_candidates
from ..stages.run import check_compares, create_stages, in_stage, retrieval_depth, run_stages, track_of


def load_data(spec: RunSpec, settings: RunSettings):
    """The spec's dataset under its protocol, checked to be the one the spec names."""
    from ..datasets import load_dataset

    if spec.dataset.kind == "given":  # made by hand: nothing on disk names it (a benchmark's name would load another)
        raise VPRBenchError(f"The spec's dataset {spec.dataset.name!r} was given as a Dataset made in Python "
                            f"({spec.dataset.protocol_id}): pass it again, evaluate(spec, settings, dataset=...).")
    name = spec.dataset.path if spec.dataset.kind == "own" else spec.dataset.name
    dataset = load_dataset(name, settings.data_dir, strict=settings.strict, fetch=settings.download,
                           protocol=None if spec.dataset.kind == "own" else spec.dataset.protocol,
                           cache_dir=settings.cache_dir)
    if dataset.protocol.get("hash") != spec.dataset.protocol_hash:
        raise VPRBenchError(f"Dataset {name} now has protocol hash {dataset.protocol.get('hash')}, but the spec was "
                            f"made for {spec.dataset.protocol_hash} ({spec.dataset.protocol_id}): its images or "
                            "ground truth changed after the run was planned; run it again (a spec from a file: "
                            "build the spec again).")
    return dataset


def create_run_method(name: str, given: dict, settings: RunSettings):
    """A method with the options given, and the run's device, batch size, cache and data folders."""
    from ..loader import resolve_device
    from ..methods import create_method
    from ..spec import split_run_settings

    return create_method(name, **split_run_settings(given)[0], device=resolve_device(settings.device), batch_size=settings.batch_size,
                         cache_dir=settings.cache_dir, data_dir=settings.data_dir)


def check_found(spec: RunSpec, dataset: str, cache_dir) -> None:
    """What the spec found in the cache by name (spec.found) is what the method has just loaded:
    refitted meanwhile (a sweep's specs are made before its cells run), the record would name the
    earlier content while holding results of the new."""
    if not spec.found:
        return
    from ..methods.registry import method_entry

    now = method_entry(spec.method).cached_identities(spec.options, dataset, cache_dir)
    for option in sorted(set(now) | set(spec.found)):
        if now.get(option) != spec.found.get(option):
            raise VPRBenchError(f"{spec.method}: the {option} it names changed in the cache after this run was planned "
                                f"({spec.found.get(option, 'none')} then, {now.get(option, 'none')} now; fitted or "
                                "placed again meanwhile): run it again.")


def check_files(spec: RunSpec, cache_dir) -> None:
    """The files the spec names by content (spec.files, each stage's) hold that content still: edited since
    the spec was made (a sweep makes every spec before its cells run), the record would name the earlier
    bytes while holding results of the new, in the earlier bytes' row."""
    from ..content_identity import option_identities
    from ..spec import resolve_stage

    named = [("option", spec.method, spec.files, option_identities(spec.method, spec.options, cache_dir))]
    named += [("stage option", stage.name, stage.files, resolve_stage(stage).files) for stage in spec.stages]
    for what, owner, then, now in named:
        for option in sorted(set(then) | set(now)):
            if then.get(option) != now.get(option):
                raise VPRBenchError(f"{owner}: the file {what} {option} names changed after this run was planned "
                                    f"({then.get(option, 'none')} then, {now.get(option, 'none')} now; written again "
                                    "meanwhile): run it again.")


def loader_workers(settings: RunSettings, method) -> int:
    """--workers, else the loader's default for the method's device."""
    from ..loader import default_workers

    return settings.workers if settings.workers is not None else default_workers(str(getattr(method, "device", "cpu")))


def stage_context(spec: RunSpec, settings: RunSettings, method, dataset, described, progress,
                  fit_on=None, stages=(), candidates_k: int = 0) -> StageContext:
    """What stages see: the dataset and the retriever's descriptors as its search saw them (post-processed
    as fitted on `fit_on`, several databases stacked, when the search's was), once the budget is known
    to hold `stages` on `candidates_k` candidates per query."""
    from ..loader import resolve_device
    from .postprocess import postprocessed

    budget = settings.memory_budget or DEFAULT_MEMORY_BUDGET

    def plan(rows, asked, fit=()):  # checked before retrieval when it ran here; from exported candidates, here
        check_run_budget([*fit, *stage_needs(stages, rows, asked, candidates_k)], budget)
    database, queries, _ = postprocessed(method, described.stores["database"], described.stores["queries"], budget,
                                         fit_on=fit_on, plan=plan)
    plan(database, queries)
    prefix = {**spec.row_identity(), "stages": [], "protocol": spec.dataset.protocol_hash}
    return StageContext(dataset=dataset, database=database, queries=queries, spec=spec, prefix=prefix,
                        cache_dir=settings.cache_dir, memory_budget=budget, lock_timeout=settings.lock_timeout,
                        progress=progress, compare=getattr(method, "compare", "cosine"),
                        device=str(getattr(method, "device", None) or resolve_device(settings.device)))


def check_dataset(dataset, spec: RunSpec) -> None:
    """A dataset given already built must be the spec's (its protocol and its name)."""
    from ..datasets import Dataset

    require(dataset, Dataset, "dataset takes a vprbench Dataset (vprbench.datasets.load_dataset(name)), or None to "
                              "load the spec's")
    protocol = protocol_of(dataset)
    if protocol["hash"] != spec.dataset.protocol_hash:
        raise VPRBenchError(f"The dataset given is {protocol['id']}, not the spec's {spec.dataset.protocol_id}.")
    if dataset.name != spec.dataset.name:  # the record names its dataset by this name
        raise VPRBenchError(f"The dataset given is named {dataset.name!r}, but its protocol is the spec's dataset "
                            f"{spec.dataset.name!r}: a dataset cannot be renamed; load it with load_dataset.")


@dataclass
class Retrieved:
    """A run up to its candidates: what evaluate and `candidates export` share."""

    method: object
    dataset: object
    ks: tuple[int, ...]
    described: object
    found: object  # SearchResult: scores, indices, info
    timings: dict
    workers: int
    frozen: dict | None = None  # the candidates file the run started from
    fit_on: object = None  # the databases stacked its post-processor is fitted on (joint.py), or None
    joint: dict | None = None  # what each of them is


def retrieved(spec: RunSpec, settings: RunSettings, stages, *, dataset=None, method=None, progress=None,
              ranks: Ranks | None = None, depth: int | None = None) -> Retrieved | None:
    """Load, describe (stores) and search (or read `settings.candidates`): the top candidates of
    `spec`'s retriever, as deep as its stages need (or `depth`). None on ranks other than 0."""
    ranks = ranks or Ranks()
    if dataset is not None:  # before a method is built (it may load weights)
        check_dataset(dataset, spec)
    if method is None:
        method = create_run_method(spec.method, spec.written or spec.given, settings)  # checked before data is read
    else:
        check_method(method, spec)
        if settings.batch_size is not None:  # honoured (and checked) for a method given as for one created here
            size = checked_run_options(method.name, {"batch_size": settings.batch_size})["batch_size"]
            set_attributes(method, method.name, source_of(type(method)), batch_size=size)
    check_compare(spec.method, getattr(method, "compare", "cosine"), spec.search.index, spec.search.options)
    ranks.agree({"spec": spec.key, "cache": str(settings.cache_dir.resolve()) if settings.cache_dir else None,
                 "data": str(settings.data_dir) if settings.data_dir else None,
                 # how it runs too (the record names rank 0's settings for every rank's rows); not the device,
                 # which a rank may name by its own GPU (cuda:1)
                 "run": {k: v for k, v in settings.describe().items() if k != "device"}}, "the run (spec, cache folder, data root, run settings)")
    if dataset is None:
        dataset = ranks.on_zero(lambda: load_data(spec, settings))  # fetched on first use by rank 0 alone
    ks = ks_within_database(spec.ks, len(dataset.database), dataset.name)
    for stage in stages:  # before any descriptor is computed
        with in_stage(stage, "check"):
            stage.check(dataset)
    check_compares(stages, getattr(method, "compare", "cosine"))
    depth = depth or retrieval_depth(stages, ks, len(dataset.database), dataset.name)
    if depth > len(dataset.database):
        raise VPRBenchError(f"{depth} candidates per query asked for, but the database of {dataset.name} holds "
                            f"{len(dataset.database)} images: ask for at most {len(dataset.database)}.")
    if settings.candidates is None and spec.search.approximate:  # a database too small for its index: refused now
        sized_options(spec.search.index, len(dataset.database), depth, spec.search.options)
    frozen = None
    if settings.candidates is not None:  # checked before any descriptor is computed
        frozen = read_candidates(settings.candidates, spec, len(dataset.queries), len(dataset.database), depth,
                                 images_identity(dataset, settings.cache_dir))
    use_dataset(method, dataset.name)
    check_found(spec, dataset.name, settings.cache_dir)
    check_files(spec, settings.cache_dir)
    members = joint_members(method, dataset, settings, ranks)
    if members is None:
        check_database_size(method, len(dataset.database), dataset.name)
    else:
        check_database_size(method, sum(len(m.database) for m in members),
                            f"the databases of {', '.join(m.name for m in members)} stacked")
    workers = loader_workers(settings, method)
    described = describe_splits(
        method, {"database": dataset.database, "queries": dataset.queries}, root=dataset.root, label=dataset.name,
        digests=dataset.image_digests(settings.cache_dir), names=dataset.image_names(), cache_dir=settings.cache_dir,
        store_dtype=spec.store_dtype, workers=workers, lock_timeout=settings.lock_timeout, ranks=ranks,
        progress=progress, settings=spec.options)  # keyed as the spec: one run, one store
    restamp_fingerprint(method)  # as this run left it (weights loaded): the same object may run again
    budget, compare = settings.memory_budget or DEFAULT_MEMORY_BUDGET, getattr(method, "compare", "cosine")

    def plan(rows, asked, fit=()):  # the fit's need, and the rows as the search and the stages read them
        search = [] if frozen is not None else [(f"retrieval's {spec.search.index} search", retrieval_need(
            compare, rows, asked, depth, spec.search.index, spec.search.options or None))]
        check_run_budget([*fit, *search, *stage_needs(stages, rows, asked, depth)], budget)
    fit_on, joint, t = None, None, time.perf_counter()
    if members is not None:  # every rank describes its share of each, once the stack's fit is known to fit
        stacked = sum(len(m.database) for m in members)
        ranks.on_zero(lambda: check_joint_budget(method, stacked, described.stores, budget, plan))
        fit_on, joint = describe_members(spec, settings, method, dataset, members, described, workers=workers,
                                         ranks=ranks, progress=progress)
    if described.stores is None:  # not rank 0: its shard is written; rank 0 evaluates
        return None
    timings = {"fit_s": described.timings["fit_s"], "database_s": described.timings["database_s"],
               "queries_s": described.timings["queries_s"],
               **({"stack_s": time.perf_counter() - t} if members else {})}  # the other databases of the stack
    t = time.perf_counter()
    if frozen is not None:
        found = frozen.pop("found")
    else:
        memory = {} if settings.memory_budget is None else {"memory_budget": settings.memory_budget}
        database, queries = described.stores["database"], described.stores["queries"]
        with phase(progress, f"{method.name} {dataset.name} search ({spec.search.index}, {queries.row_count:,} queries "
                             f"x {database.row_count:,} database)"):
            found = retrieve(method, database, queries, depth, index=spec.search.index,
                             index_options=spec.search.options or None, fit_on=fit_on, check=plan, **memory)
    timings["search_s"] = time.perf_counter() - t
    return Retrieved(method, dataset, ks, described, found, timings, workers, frozen, fit_on, joint)


def evaluate(spec: RunSpec, settings: RunSettings | None = None, *, dataset=None, method=None, progress=None,
             ranks: Ranks | None = None) -> dict | None:
    """Recall@K and PR metrics of the run `spec` names, with a full result record (not saved:
    `vprbench.evaluation.save_result` stores it).

    `settings` say how it runs and where the data and cache are (default: the user cache and the
    default data root). `dataset`/`method` may be given already built (e.g. a dataset made by
    hand); they must be the spec's (a method its name, class and options, and its fingerprint as
    `create_method` made it: make the spec with `spec_for(method, dataset)`; a dataset its
    protocol), and `settings.batch_size` applies to a method given too. Under torchrun (`ranks`
    from `Ranks.from_environment()`) every rank describes its shard; rank 0 returns the record,
    the other ranks None. A run with stages may start from exported candidates
    (`settings.candidates`, vprbench/stages/candidates.py).
    """
    started = time.perf_counter()
    require(spec, RunSpec, "evaluate(spec) takes a RunSpec: make one with vprbench.spec.resolve_spec(name, dataset) "
                           "or spec_for(method, dataset)")
    settings = RunSettings() if settings is None else settings
    require(settings, RunSettings, "evaluate's settings take a vprbench.spec.RunSettings(cache_dir=..., data_dir=...), "
                                   "or None for the defaults")
    ranks = Ranks() if ranks is None else ranks
    require(ranks, Ranks, "evaluate's ranks take a vprbench.distributed.Ranks (Ranks.from_environment() under "
                          "torchrun), or None for one process")
    if progress is not None and not callable(getattr(progress, "add_task", None)):  # else found out mid-run
        raise VPRBenchError(f"evaluate's progress takes a rich Progress (or vprbench.progress's log one), or None; "
                            f"got {type(progress).__name__}.")
    stages = create_stages(spec)  # their options are checked before any data is touched
    if settings.candidates is not None and not stages:
        raise VPRBenchError(f"--candidates {settings.candidates} gives the candidates a re-ranking starts from, but "
                            "this run has no stage: add --rerank STAGE (or drop --candidates).")
    if settings.candidates is not None and stages[0].track == "sequence":  # it would be named in the record, unused
        raise VPRBenchError(f"--candidates {settings.candidates} gives the candidates a re-ranking starts from, but "
                            f"sequence stage {stages[0].name!r} runs first and matches every query against the whole "
                            "database, ignoring them: drop --candidates (or the sequence stage).")
    run = retrieved(spec, settings, stages, dataset=dataset, method=method, progress=progress, ranks=ranks)
    if run is None:
        return None
    method, dataset, described, found, timings = run.method, run.dataset, run.described, run.found, run.timings
    candidates, stage_costs = Candidates(found.indices, found.scores), []
    if stages:
        t = time.perf_counter()
        context = stage_context(spec, settings, method, dataset, described, progress, run.fit_on, stages,
                                candidates.k)
        if run.frozen is not None:  # a file's rows checked against the descriptors before a stage re-ranks them
            check_scores(settings.candidates, found, context.database, context.queries, context.compare,
                         context.memory_budget)
        flags = None if found.all_zero is None else found.all_zero.failures(track_of(stages))
        candidates, stage_costs = run_stages(stages, candidates, context, run.ks, dataset.positives, flags)
        timings["stages_s"] = time.perf_counter() - t
    candidates = candidates.top(run.ks[-1])
    timings["total_s"] = time.perf_counter() - started
    # where the descriptors are (vprbench.store.run_store): one folder per split
    context = {"store": {"folders": dict(described.folder.keys)}}
    if ranks.distributed:
        context["distributed"] = {**ranks.describe(), "computed_per_rank": described.per_rank}
    if run.joint is not None:
        context["postprocess_datasets"] = run.joint  # the databases its post-processor was fitted on
    if run.frozen is not None:
        context["candidates"] = run.frozen  # the file the re-ranking started from
    return result_record(
        spec=spec, method=method, fingerprint=described.fingerprint, dataset=dataset,
        dataset_key=dataset.fingerprint(settings.cache_dir), ks=run.ks,
        scores=candidates.scores, indices=candidates.indices, positives=dataset.positives,
        descriptor_dim=int(found.info["dim"]), computed=described.computed, timings=timings, search=found.info,
        context=context, run={**settings.describe(), "device": str(getattr(method, "device", settings.device)),
                              "workers": run.workers, "batch_size": method.batch_size},
        cache_dir=settings.cache_dir, track=track_of(stages), stages=stage_costs, all_zero=found.all_zero,
    )


#: candidates per query `candidates export` writes unless given --k
DEFAULT_K = 100


def export_candidates(spec, settings, path, k: int = DEFAULT_K, progress=None) -> dict:
    """Search with `spec`'s retriever (its stores described as evaluate would) and write the top `k`
    per query to `path`. Returns what was written (path, queries, k)."""
    if spec.stages:
        raise VPRBenchError("candidates export writes a retriever's candidates: give the method without stages "
                            "(no --rerank or --sequence).")
    if settings.candidates is not None:
        raise VPRBenchError("candidates export searches; it does not start from --candidates.")
    # the search as deep as it runs; no Recall@K is computed: the default K (up to 20) was checked against the
    # database and told to lower --k, which here is the depth (checked by `retrieved`, named as such)
    spec = spec.model_copy(update={"search": searched_to(spec.search, _depth(k)), "ks": (1,)})
    run = retrieved(spec, settings, [], progress=progress, depth=k)
    write_candidates(path, spec, run.found, images_identity(run.dataset, settings.cache_dir))
    return {"file": str(path), "queries": int(run.found.indices.shape[0]), "k": int(run.found.indices.shape[1])}


def _depth(k) -> int:
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise VPRBenchError(f"--k takes a whole number >= 1 of candidates per query, got {k!r}.")
    return k
