"""Store folders: the descriptors of one method (fingerprint) on one split's images.

    stores/<method>-<fingerprint key>/<label>-<split>-<split key>/   one folder per split
        database.h5 (or queries.h5)             the split's complete store
        database.rank0-of-2.partial.h5 ...      shards being written (one per rank; 1 rank = 1 shard)
        fit_state.h5                            (database folder) what the method fitted on it
        .lock (+ .lock.holder)                  held by the one process that writes here

A split's key is its own images' content (plus, for a method that fits, the database images
its rows depend on through the fit): editing a query recomputes only the queries. Only the
lock holder creates, discards or renames files in a folder (ranks of a distributed run
write their own shards while their rank 0 holds the locks). Complete stores are never changed
after they appear, so readers need no lock; a reader that finds one damaged (a row that
fails its checksum) discards it under the lock. The key is the content identity of the
images, not of the ground truth: a new radius re-scores the same stores.
"""
from __future__ import annotations

import hashlib
import json
import uuid
import warnings
from contextlib import ExitStack, contextmanager, suppress
from pathlib import Path

import h5py
import numpy as np

from ..errors import ShardWarning, VPRBenchError
from ..fsutil import CacheError, atomic_path, cache_error, is_temporary, lock
from ..paths import cache_root, safe_name, special_file
from ..hashing import canonical_hash, canonical_json
from ..methods.attributes import own_fingerprint
from ..run_settings import RUN_SETTINGS
from .reader import DescriptorStore
from .rows_file import DamagedRows, RowsIdentity, folder_lock, hdf5_written, inspect_rows_file

#: fit id of methods that fit nothing
NO_FIT = "none"
#: the store key's own entries beside a method's fingerprint() ("method" too, which AnyLoc's
#: fingerprint sets to its family name: the folder is named after the method either way)
RESERVED_KEYS = ("settings", "store_dtype", "decoding")


def method_fingerprint(method, store_dtype: str = "float32", settings: dict | None = None, cache_dir=None) -> dict:
    """What the store is keyed by: the method's name, its merged options (even those its own
    `fingerprint()` forgets), its fingerprint and the stored dtype. An evaluation gives `settings`,
    its spec's options: normalised as the spec is (an option naming the dataset evaluated is as
    unset), so a method created with it shares the store of one created without. An option naming a
    file or folder is keyed by its content, as the spec names it (`RunSpec.files`)."""
    if settings is None:
        settings = getattr(method, "settings", None)
    if not isinstance(settings, dict):  # until the registry sets `settings`, the user's options
        settings = method.options
    from ..content_identity import option_identities
    from ..images import ORIENTATION

    settings = {k: v for k, v in sorted(settings.items()) if k not in RUN_SETTINGS}
    # by path, the file edited in place kept its store: a run whose spec names the new bytes read the old ones'
    files = option_identities(method.name, settings, cache_dir if cache_dir is not None else getattr(method, "cache_dir", None))
    settings = {k: files.get(k, v) for k, v in settings.items()}
    own = own_fingerprint(method)
    clash = sorted(set(own) & set(RESERVED_KEYS))  # its own key would overwrite what keeps two stores apart
    if clash:
        raise VPRBenchError(f"Method {method.name!r}: fingerprint() uses the key(s) {', '.join(clash)}, which the "
                            f"store's key sets itself ({', '.join(RESERVED_KEYS)}); rename them in the method.")
    return json.loads(json.dumps({"method": method.name, "settings": settings, **own,
                                  "store_dtype": store_dtype, "decoding": {"orientation": ORIENTATION}}, default=str))


def run_store(record: dict, split: str = "database", cache_dir=None) -> DescriptorStore | None:
    """The complete store an evaluation's result record was computed from (its
    context.store.folders, or .folder for records of the one-folder layout), or None when the
    record does not name one or the store is gone."""
    store = (record.get("context") or {}).get("store") or {}
    folder = (store.get("folders") or {}).get(split) if "folders" in store else store.get("folder")
    if not folder:
        return None
    return DescriptorStore.recorded(cache_root(cache_dir) / "stores" / folder / f"{split}.h5", f"{folder}/{split}")



def shard_range(total: int, rank: int, world: int) -> tuple[int, int]:
    """Rows [start, stop) of rank `rank` among `world` contiguous shards."""
    return total * rank // world, total * (rank + 1) // world


def fit_id_of(state: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for key in sorted(state):
        value = np.ascontiguousarray(state[key])
        h.update(f"{key}|{value.dtype.str}|{value.shape}|".encode())
        h.update(value.tobytes())
    return "sha256:" + h.hexdigest()


def unsaved_fit_id() -> str:
    """A fit the method cannot save: nothing computed with it is ever resumed by another fit."""
    return "unsaved:" + uuid.uuid4().hex


class StoreFolder:
    """The folders of one method's splits; `split_keys` maps each split to what its rows depend on."""

    def __init__(self, method_name: str, fingerprint: dict, label: str, split_keys: dict, cache_dir=None):
        self.fingerprint = fingerprint
        self.fingerprint_json = canonical_json(fingerprint)
        # names from data made safe; the hashes keep two stores apart
        method = f"{safe_name(method_name)}-{canonical_hash(fingerprint)}"
        self.keys = {split: f"{method}/{safe_name(label)}-{safe_name(split)}-{canonical_hash(key)}"
                     for split, key in split_keys.items()}
        self.paths = {split: cache_root(cache_dir) / "stores" / key for split, key in self.keys.items()}
        fit_split = "database" if "database" in self.keys else next(iter(self.keys))
        self.fit_key = self.keys[fit_split]  # the method and the database images it was fitted on
        self.fit_path = self.paths[fit_split] / "fit_state.h5"

    def keep_database_with_queries(self) -> None:
        """A fit that cannot be saved: the database rows described with it serve this query set
        alone (another would refit and replace them under it), so they live in the queries' folder."""
        self.keys["database"], self.paths["database"] = self.keys["queries"], self.paths["queries"]

    # ------------------------------------------------------------ names
    def store_path(self, split: str) -> Path:
        return self.paths[split] / f"{split}.h5"

    def shard_path(self, split: str, rank: int, world: int) -> Path:
        return self.paths[split] / f"{split}.rank{rank}-of-{world}.partial.h5"

    def identity(self, split: str, names: list[str], fit_id: str, dtype: str,
                 start: int = 0, stop: int | None = None) -> RowsIdentity:
        stop = len(names) if stop is None else stop
        return RowsIdentity(store=f"{self.keys[split]}/{split}", start=start, stop=stop, total=len(names), fit_id=fit_id,
                            dtype=dtype, fingerprint=self.fingerprint_json, names=names[start:stop])

    # ------------------------------------------------------------ the lock
    @contextmanager
    def locked(self, timeout: float | None = None):
        """Every split folder's lock, taken in one order (by path) so two runs never deadlock."""
        with ExitStack() as held:
            for path in sorted(set(self.paths.values())):
                held.enter_context(folder_lock(path, timeout))
            yield

    # ------------------------------------------------------------ complete stores
    def complete(self, split: str, names: list[str], fit_id: str, dtype: str) -> DescriptorStore | None:
        """The split's complete store, every row checked against its checksum, or None (absent,
        partial, stale, torn, or damaged: then it is discarded under the lock and said so)."""
        path = self.store_path(split)
        identity = self.identity(split, names, fit_id, dtype)
        found = inspect_rows_file(path, identity)
        if found.status == "foreign":
            raise VPRBenchError(f"Descriptor store {path} does not belong to this store: {found.reason}. "
                                "Delete it (it is recomputed).")
        if found.status != "complete":
            return None
        store = DescriptorStore(path, identity)
        try:
            store.verify()
        except DamagedRows as damage:
            warnings.warn(f"Descriptor store {path} was damaged ({damage.detail}); it was discarded and is "
                          "recomputed.", stacklevel=2)
            return None
        return store

    def recorded_fit_id(self, split: str) -> str | None:
        """The fit id a split's complete store says it was computed with."""
        if special_file(self.store_path(split)):  # HDF5 would wait on a pipe for good (inspection discards it)
            return None
        try:
            with h5py.File(self.store_path(split), "r") as f:
                value = f.attrs.get("fit_id")
                return value.decode() if isinstance(value, bytes) else value
        except (OSError, KeyError):
            return None

    def discard(self, path: Path, reason: str) -> None:
        """Remove a file of this folder; only the lock holder calls this."""
        warnings.warn(f"Discarding {path}: {reason}; it is recomputed.", ShardWarning, stacklevel=3)
        try:
            path.unlink(missing_ok=True)
        except OSError as error:
            raise cache_error(error, path) from None

    def tidy(self, split: str) -> None:
        """After the split's store is complete: its shards (any number of ranks) and any
        leftovers of killed writers go. Only the lock holder calls this."""
        folder = self.paths[split]
        try:
            for path in folder.glob(f"{split}.rank*-of-*.partial.h5"):
                path.unlink(missing_ok=True)
            for path in folder.iterdir():  # only this split's and the fit state's: others write theirs unlocked
                if is_temporary(path) and path.name.startswith((f".{split}.", f".{self.fit_path.name}.")):
                    path.unlink(missing_ok=True)
        except OSError as error:
            raise cache_error(error, folder) from None

    def tidy_if_free(self, split: str) -> None:
        """A complete store is served without the lock, so a writer killed between its rename and
        `tidy` would leave its shards (the store's size again) for good: remove them now, if no
        other run holds the lock (one that does tidies itself). Best effort: a read-only cache keeps them."""
        folder = self.paths[split]
        try:
            leftover = any(folder.glob(f"{split}.rank*-of-*.partial.h5")) or any(
                is_temporary(p) and p.name.startswith(f".{split}.") for p in folder.iterdir())
        except OSError:
            return
        if leftover:
            with suppress(CacheError), lock(folder / ".lock", 0, announce=False):  # LockTimeout is one
                self.tidy(split)

    # ------------------------------------------------------------ fit state
    def fit_id_on_disk(self) -> str | None:
        if special_file(self.fit_path):  # HDF5 would wait on a pipe for good (read_fit_state discards it)
            return None
        try:
            with h5py.File(self.fit_path, "r") as f:
                value = f.attrs["fit_id"]
                return value.decode() if isinstance(value, bytes) else value
        except (OSError, KeyError):
            return None

    def read_fit_state(self) -> tuple[dict[str, np.ndarray], str] | None:
        """(state, fit id), or None when there is none; a file that cannot be read is discarded
        (only the lock holder calls this)."""
        if not self.fit_path.exists():
            return None
        try:
            if special_file(self.fit_path):  # HDF5 would wait on a pipe for good
                raise ValueError("it is a named pipe, device or socket, not a file")
            with h5py.File(self.fit_path, "r") as f:
                state = {key: f["state"][key][...] for key in f["state"]}
                recorded, store = f.attrs["fit_id"], f.attrs.get("store")
            recorded = recorded.decode() if isinstance(recorded, bytes) else recorded
            if not state or fit_id_of(state) != recorded:
                raise ValueError("its content does not match its fit id")
            if (store.decode() if isinstance(store, bytes) else store) != self.fit_key:  # a copy from another store
                raise ValueError(f"it was fitted for store {store!r}, not this one")
            return state, recorded
        except (OSError, KeyError, ValueError) as error:
            if isinstance(error, PermissionError):
                raise cache_error(error, self.fit_path) from None
            self.discard(self.fit_path, f"the fit state cannot be read ({error})")
            return None

    def write_fit_state(self, state: dict[str, np.ndarray]) -> str:
        """Saved whole or not at all (written aside, then renamed): a kill at any moment leaves
        the old state or the new one. Returns the fit id."""
        state = {key: np.asarray(value) for key, value in state.items()}
        fit_id = fit_id_of(state)
        with atomic_path(self.fit_path) as temporary:
            with hdf5_written(temporary, self.fit_path) as f:
                group = f.create_group("state")
                for key, value in state.items():
                    group.create_dataset(key, data=value)
                f.attrs["fit_id"] = fit_id
                f.attrs["store"] = self.fit_key  # the method and the database images it was fitted on
        return fit_id
