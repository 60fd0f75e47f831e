"""Descriptors of image splits through the store, shared by `evaluate` and `describe`.

1. Rank 0 looks for complete stores (no lock needed: complete stores never change).
2. Otherwise rank 0 takes the store folder's lock (waiting for, then reusing, another run's
   work), fits the method on the database split or loads the saved fit, and hands the fit
   to the other ranks.
3. Every rank describes the missing rows of its shard of each unfinished split into its
   own shard file (resumable on its own: only rows not flagged done are described).
4. Rank 0 stitches the shards into the split's store (one shard: a rename; several: a
   merge into one file), then releases the lock.
A single process is rank 0 of 1: the same steps, one shard per split.
"""
from __future__ import annotations

import os
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..datasets.identity import check_store_names, content_hashes, image_names, images_key
from ..distributed import Ranks
from ..errors import VPRBenchError
from ..fsutil import cache_error
from ..images import reads_seen
from ..loader import check_batch_size, describe_batches, plugin_part
from ..store import (DTYPES, NO_FIT, DamagedRows, DescriptorStore, RowWriter, StoreFolder, create_rows_file, inspect_rows_file,
                     method_fingerprint, shard_range)
from ..store.folder import unsaved_fit_id
from ..store.rows_file import merge_rows_files
from ..progress import phase
from ..text import shortened

#: the split a method fits on (and PCA-whitening is fitted on)
FIT_SPLIT = "database"


@dataclass
class Described:
    """The complete stores (rank 0 only; None elsewhere), what was computed now and how long it took."""

    stores: dict[str, DescriptorStore] | None
    computed: dict[str, int]
    timings: dict[str, float]
    fingerprint: dict
    folder: StoreFolder
    per_rank: list[dict[str, int]] = field(default_factory=list)


def describe_splits(method, splits: dict[str, list[Path]], *, root: Path | None = None, label: str = "images",
                    digests: dict[str, list[str]] | None = None, names: dict[str, list[str]] | None = None,
                    cache_dir=None, store_dtype: str = "float32",
                    workers: int = 0, lock_timeout: float | None = None, ranks: Ranks | None = None,
                    progress=None, settings: dict | None = None) -> Described:
    """Complete stores for every split of `splits` (name -> image paths), computing what is missing.
    `digests` are the images' sha256 per split (hashed now when not given): the store is keyed by
    them, and every image described is checked to still have them (loader.py). `names` are the
    images' names per split (`image_names` of `root`; made now when not given). `settings` are the
    options the store is keyed by when not the method's own (an evaluation's: its spec's)."""
    ranks = ranks or Ranks()
    if store_dtype not in DTYPES:
        raise VPRBenchError(f"--store-dtype must be one of {', '.join(DTYPES)}, got {store_dtype!r}.")
    check_batch_size(method)
    for split, paths in splits.items():
        if not paths:
            raise VPRBenchError(f"No images to describe in the {split} split.")
    names = names or {split: image_names(paths, root) for split, paths in splits.items()}
    for split, paths in splits.items():
        check_store_names(paths, names[split])
    digests = digests or {split: content_hashes(paths, cache_dir) for split, paths in splits.items()}
    image_keys = {split: images_key(paths, root, digests=digests[split], names=names[split]) for split, paths in splits.items()}
    fingerprint = method_fingerprint(method, store_dtype, settings, cache_dir)
    folder = StoreFolder(method.name, fingerprint, label, split_keys(method, image_keys), cache_dir)
    if (method.needs_fit and "queries" in splits and not folder.fit_path.exists()
            and (folder.paths["queries"] / f"{FIT_SPLIT}.h5").exists()):  # described with a fit never saved
        folder.keep_database_with_queries()
    ranks.agree({"fingerprint": fingerprint, "images": image_keys,
                 "store": {split: str(path.resolve()) for split, path in folder.paths.items()}},
                "the method, the images or the cache folder")
    job = _Job(method, splits, names, folder, store_dtype, workers, ranks, progress, label, digests, cache_dir)
    computed = {split: 0 for split in splits}
    timings = {"fit_s": 0.0, **{f"{split}_s": 0.0 for split in splits}}

    stores = job.complete_stores() if ranks.rank == 0 else None
    if ranks.broadcast(stores is not None):
        for split in stores or ():
            folder.tidy_if_free(split)
        # one entry per rank, as when they compute: nothing, on every rank
        per_rank = [dict(computed) for _ in range(ranks.world_size)]
        # the other ranks hold no stores: rank 0 alone found them complete
        return Described(same_dim(method, stores) if stores is not None else None, computed, timings, fingerprint,
                         folder, per_rank)
    with ExitStack() as held:
        def plan():
            with plugin_part(method, "prepare"):  # a bad weights file is refused before the folders exist
                method.prepare()
            for paths in splits.values():  # so is what every image shares (too small, a format not read)
                with plugin_part(method, "load", on=f"image {paths[0]}"):
                    method.load(paths[0])
            held.enter_context(folder.locked(lock_timeout))
            return job.plan(timings)

        todo, fit_id, state = ranks.on_zero(plan)
        if ranks.rank != 0 and state:
            with plugin_part(method, "load_fit_state"):
                method.load_fit_state(state)
        for split in todo:
            started = time.perf_counter()
            computed[split] = job.extract_shard(split, fit_id)
            timings[f"{split}_s"] = time.perf_counter() - started
        per_rank = ranks.all_gather(computed)
        if ranks.rank != 0:
            return Described(None, computed, timings, fingerprint, folder, per_rank)
        for split in todo:
            started = time.perf_counter()
            job.stitch(split, fit_id)
            timings[f"{split}_s"] += time.perf_counter() - started
        stores = job.complete_stores()
    if stores is None:
        raise VPRBenchError(f"The stores in {', '.join(map(str, folder.paths.values()))} are still incomplete after "
                            "extraction; run again.")
    totals = {split: sum(c[split] for c in per_rank) for split in splits}
    return Described(same_dim(method, stores), totals, timings, fingerprint, folder, per_rank)


def same_dim(method, stores: dict) -> dict:
    """`stores`, or an error naming the method when its splits' rows differ in dimension (each
    store is what it computed for its images; only their comparison is impossible)."""
    dims = {split: store.dim for split, store in stores.items()}
    if len(set(dims.values())) > 1:
        found = " and ".join(f"the {split} in {dim}" for split, dim in dims.items())
        raise VPRBenchError(f"Method {method.name!r} described {found} dimensions: every image must get the same "
                            "dimension to be compared; fix the method.")
    return stores


def split_keys(method, image_keys: dict[str, str]) -> dict:
    """What each split's store is keyed by: its own images, and for a method that fits, the
    database images the fit (so every row) depends on; editing a query keeps the database's."""
    if not method.needs_fit:
        return dict(image_keys)
    return {split: key if split == FIT_SPLIT else {"images": key, "fit_on": image_keys.get(FIT_SPLIT)}
            for split, key in image_keys.items()}


class _Job:
    def __init__(self, method, splits, names, folder: StoreFolder, dtype, workers, ranks: Ranks, progress, label,
                 digests, cache_dir=None):
        self.method, self.splits, self.names, self.folder, self.digests = method, splits, names, folder, digests
        self.cache_dir = cache_dir  # the content memo's (datasets.identity.content_hashes)
        self.dtype, self.workers, self.ranks, self.progress, self.label = dtype, workers, ranks, progress, label

    # ---------------------------------------------------------------- rank 0
    def expected_fit_id(self) -> str | None:
        if not self.method.needs_fit:
            return NO_FIT
        return self.folder.fit_id_on_disk() or self.folder.recorded_fit_id(FIT_SPLIT)

    def complete_stores(self) -> dict[str, DescriptorStore] | None:
        """Every split's complete store, all computed with the same fit, or None."""
        fit_id = self.expected_fit_id()
        if fit_id is None:
            return None
        stores = {}
        for split in self.splits:
            store = self.folder.complete(split, self.names[split], fit_id, self.dtype)
            if store is None:
                return None
            stores[split] = store
        return stores

    def plan(self, timings: dict) -> tuple[list[str], str, dict | None]:
        """Under the folder lock: (splits to extract, fit id, fit state for the other ranks)."""
        if self.complete_stores() is not None:  # another run finished while we waited
            return [], self.expected_fit_id(), None
        fit_id, state = NO_FIT, None
        if self.method.needs_fit:
            if FIT_SPLIT not in self.splits:
                raise VPRBenchError(f"Method {self.method.name!r} fits on database images: give them "
                                    "(describe --fit-on FOLDER).")
            found = self._saved_fit()
            if found is not None:
                state, fit_id = found
            else:
                started = time.perf_counter()
                with phase(self.progress if self.ranks.rank == 0 else None,
                           f"{self.method.name} {self.label} fitting on {len(self.splits[FIT_SPLIT]):,} database images"):
                    with reads_seen() as seen, plugin_part(self.method, "fit"):
                        # a copy: a fit that sorts or shuffles its list would reorder the rows described next
                        self.method.fit(list(self.splits[FIT_SPLIT]))
                self._check_fitted_images(seen)
                timings["fit_s"] = time.perf_counter() - started
                state = fitted_state(self.method)
                if state:
                    fit_id = self._save_fit(state)
                elif self.ranks.distributed:
                    raise VPRBenchError(f"Method {self.method.name!r} fits on the database but its fit_state() is "
                                        "empty, so other ranks cannot share the fit: run it in one process.")
                else:
                    fit_id = unsaved_fit_id()  # nothing described with an unsaved fit is ever resumed
                    if "queries" in self.splits:
                        self.folder.keep_database_with_queries()
        todo = []
        for split in self.splits:
            path = self.folder.store_path(split)
            found = inspect_rows_file(path, self.folder.identity(split, self.names[split], fit_id, self.dtype))
            if found.status == "complete":
                continue
            if found.status == "foreign":
                raise VPRBenchError(f"Descriptor store {path} does not belong to this store: {found.reason}. Delete it.")
            if found.status in ("stale", "torn", "partial"):
                self.folder.discard(path, found.reason or "it is not complete")
            todo.append(split)
        return todo, fit_id, state if self.ranks.distributed else None

    def _saved_fit(self) -> tuple[dict, str] | None:
        """(state, fit id) of the saved fit, loaded into the method; None when there is none, or the
        method refuses it (its fit id is a hash anyone may write again over edited or crafted centres):
        that file is discarded, said in a warning, and the method fits again. Before this, the stores it
        no longer matched were discarded and the run failed on it, every time, without naming it."""
        found = self.folder.read_fit_state()
        if found is None:
            return None
        refused = None
        with plugin_part(self.method, "load_fit_state"):
            try:
                self.method.load_fit_state(found[0])
            except (VPRBenchError, ValueError, KeyError) as error:  # as a post-processor's load_state
                refused = error
        if refused is None:
            return found
        self.folder.discard(self.folder.fit_path, f"the method refuses it ({shortened(str(refused).rstrip('.'), 200)})")
        return None

    def _check_fitted_images(self, seen: dict[str, str]) -> None:
        """The fit is saved under the database's key: refuse it when an image it read (or one it may
        have read outside load_image: its content now, by the memo, so a stat unless it changed) is not
        the one that key names (edited meanwhile)."""
        paths = self.splits[FIT_SPLIT]
        unseen = [p for p in paths if os.path.abspath(p) not in seen]
        now = dict(zip(map(os.path.abspath, unseen), content_hashes(unseen, self.cache_dir)))
        for path, expected in zip(paths, self.digests[FIT_SPLIT]):
            got = seen.get(os.path.abspath(path)) or now[os.path.abspath(path)]
            if got != expected:
                raise VPRBenchError(f"Image {path} changed while {self.method.name} fitted on the database (sha256 "
                                    f"{expected[:12]}… expected, {got[:12]}… read): the fit is not saved. Let "
                                    "whatever is writing the images finish, then run again.")

    def _save_fit(self, state: dict) -> str:
        try:
            return self.folder.write_fit_state(state)
        except TypeError as error:
            raise VPRBenchError(FIT_STATE.format(name=self.method.name, error=error)) from None

    def stitch(self, split: str, fit_id: str) -> None:
        """The ranks' complete shards -> the split's store; then the shards go."""
        names, world = self.names[split], self.ranks.world_size
        parts, dims = [], set()
        for rank in range(world):
            start, stop = shard_range(len(names), rank, world)
            if start == stop:
                continue
            path = self.folder.shard_path(split, rank, world)
            identity = self.folder.identity(split, names, fit_id, self.dtype, start, stop)
            found = inspect_rows_file(path, identity)
            if found.status != "complete":
                raise VPRBenchError(f"Shard {path} of rank {rank} is {found.status} ({found.reason or 'rows missing'}); "
                                    "run again to resume it.")
            parts.append((path, identity))
            dims.add(found.dim)
        if len(dims) != 1:
            raise VPRBenchError(f"The shards of {split} in {self.folder.paths[split]} have different dimensions {sorted(dims)}.")
        final = self.folder.store_path(split)
        try:
            if world == 1:
                os.replace(parts[0][0], final)  # the one shard covers every row: it is the store
            else:
                merge_rows_files(parts, final, self.folder.identity(split, names, fit_id, self.dtype), dims.pop())
        except OSError as error:
            raise cache_error(error, final) from None
        except DamagedRows as damage:
            self.folder.discard(damage.path, damage.detail)
            raise VPRBenchError(f"Shard {damage.path} was damaged ({damage.detail}); it was discarded: run again "
                                "to recompute it.") from None
        self.folder.tidy(split)

    # ---------------------------------------------------------------- every rank
    def extract_shard(self, split: str, fit_id: str) -> int:
        """Describe this rank's missing rows of `split`; returns how many were described."""
        paths, names = self.splits[split], self.names[split]
        rank, world = self.ranks.rank, self.ranks.world_size
        start, stop = shard_range(len(paths), rank, world)
        if start == stop:
            return 0
        path = self.folder.shard_path(split, rank, world)
        identity = self.folder.identity(split, names, fit_id, self.dtype, start, stop)
        found = inspect_rows_file(path, identity)
        if found.status == "foreign":
            raise VPRBenchError(f"Shard {path} is from another run ({found.reason}); it was not written for this "
                                "method, these images and this number of ranks. Delete it and run again.")
        if found.status in ("stale", "torn"):
            self.folder.discard(path, found.reason)
        if found.status == "complete":
            return 0
        done = found.done if found.status == "partial" else np.zeros(stop - start, dtype=bool)
        todo = np.flatnonzero(~done) + start
        writer = RowWriter(path, identity) if found.status == "partial" else None
        task = None
        if self.progress is not None and rank == 0:
            suffix = f" (rank 0 of {world})" if world > 1 else ""
            task = self.progress.add_task(f"{self.method.name} {self.label} {split}{suffix}", total=stop - start,
                                          completed=stop - start - len(todo))
        device = str(getattr(self.method, "device", "cpu"))
        try:
            for offset, descriptors in describe_batches(self.method, [paths[i] for i in todo], workers=self.workers,
                                                        digests=[self.digests[split][i] for i in todo],
                                                        device=device):
                rows = todo[offset:offset + len(descriptors)]
                if writer is None:
                    create_rows_file(path, identity, descriptors.shape[1])
                    writer = RowWriter(path, identity)
                elif descriptors.shape[1] != writer.dim:
                    raise VPRBenchError(f"Method {self.method.name!r} now returns {descriptors.shape[1]} dimensions but "
                                        f"{path} holds {writer.dim}; its fingerprint() misses an option. Delete the file.")
                writer.write(rows, descriptors)
                if task is not None:
                    self.progress.advance(task, len(rows))
            writer.finish()
        finally:
            if writer is not None:
                writer.close()
        return len(todo)


FIT_STATE = "Method {name!r}: fit_state() must map names to numeric arrays ({error})."


def fitted_state(method) -> dict:
    """What the method's fit_state() returned, as arrays: a value that is no dict of arrays is one line
    naming the method (converted outside plugin_part, whose line would be vprbench's, named as the plugin's)."""
    with plugin_part(method, "fit_state"):
        state = method.fit_state() or {}
    try:
        if not isinstance(state, dict):
            raise TypeError(f"got {type(state).__name__}")
        return {k: np.asarray(v) for k, v in state.items()}
    except (TypeError, ValueError) as error:
        raise VPRBenchError(FIT_STATE.format(name=method.name, error=error)) from None
