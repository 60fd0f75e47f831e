"""The one batching loop: images -> `Method.load` in DataLoader workers -> `Method.describe`.

Workers decode and preprocess (`load`) while the main process describes the previous
batch, so an accelerator is not left waiting for JPEG decoding. Batches keep input order
and a row never depends on its batch (the `Method` contract), so descriptors are the same
for any number of workers and any batch size.

Given the images' identities (sha256 of their bytes, datasets/identity.py), a row is described
only when the very bytes decoded (`images.reads_seen`) have the identity the store is keyed
by, so a file that changed since (a sync tool, a second copy being written) never ends in a
store that claims the original bytes. A method that reads its files without `load_image` is
checked by hashing each file just before and just after its `load`.
"""
from __future__ import annotations

import contextlib
import functools
import os
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from .errors import VPRBenchError
from .images import reads_seen
from .row_sources import MAX_LENGTH, UNIT_TOLERANCE, ZERO_LENGTH


def resolve_device(device: str | None) -> str:
    """"auto" (or None): cuda when a CUDA GPU is available, else cpu."""
    if device is None or str(device).lower() == "auto":
        import torch

        return "cuda" if torch.cuda.is_available() else "cpu"
    return str(device)


def default_workers(device: str) -> int:
    """0 on CPU: decoding and describing share the same cores, so workers only add process
    start-up and copying. On an accelerator a few workers keep it fed."""
    if str(device).startswith("cpu"):
        return 0
    return max(1, min(4, (os.cpu_count() or 2) - 1))


def loaded(method, items: Sequence) -> list:
    """`items` with any path still to be read passed through `method.load` (so `describe`
    accepts paths as well as what `load` returns)."""
    return [method.load(Path(x)) if isinstance(x, (str, os.PathLike)) else x for x in items]


def plugin_failure(owner, part: str, error: BaseException, who: str | None = None,
                   attribute: bool = False, on: str | None = None) -> str | None:
    """One line for what a plugin's `part` (describe, load, fit, ..., or an `attribute` read) raised, naming `who` (default: the
    method `owner`), what it was given (`on`: the images), its package and the line of its code that raised
    (its user is not its author: a traceback through vprbench helps neither); None for vprbench's own code (a
    bug of vprbench's keeps its traceback) and for what the command already says in a line (vprbench's errors,
    paths, memory)."""
    import traceback

    top = (getattr(owner, "__module__", None) or type(owner).__module__ or "").split(".")[0]
    if top == "vprbench" or isinstance(error, (VPRBenchError, OSError, MemoryError, KeyboardInterrupt)) or (
            isinstance(error, RuntimeError) and "memory" in str(error)):  # torch's out of memory
        return None
    module = sys.modules.get(top)
    file = getattr(module, "__file__", None) or "?"
    frames = traceback.extract_tb(error.__traceback__)
    if hasattr(module, "__path__"):  # a package: its folder
        own = [f for f in frames if f.filename.startswith(os.path.dirname(file) + os.sep)]
    else:  # one module, whose folder (site-packages) holds other libraries too: its file only
        own = [f for f in frames if f.filename == file]
    own = own or frames[-1:]
    at = f" at {own[-1].filename}:{own[-1].lineno}" if own else ""
    who = who or f"Method {getattr(owner, 'name', '?')!r}"
    doing = f"reading its attribute {part}" if attribute else f"in {part}()" + (f" of {on}" if on else "")
    return (f"{who} ({top}) failed {doing}: {type(error).__name__}: "
            f"{error}{at}; fix the plugin, or report it to its authors.")


@contextlib.contextmanager
def plugin_part(owner, part: str, who: str | None = None, attribute: bool = False, on: str | None = None):
    """Runs a call into `owner`'s code (a plugin's method, stage or post-processor, or a property read): what it
    raises is the one line of `plugin_failure`, a VPRBenchError (its chain kept for a Python caller)."""
    try:
        yield
    except (Exception, SystemExit) as error:
        message = plugin_failure(owner, part, error, who, attribute, on)
        if message is None:
            raise
        raise VPRBenchError(message) from error


def postprocessor_of(method):
    """`method.postprocessor()`, what a plugin's raises as its one line."""
    with plugin_part(method, "postprocessor"):
        return method.postprocessor()


def postprocess_datasets_of(method):
    """`method.postprocess_datasets()` (the databases its post-processor is fitted on, stacked), what a
    plugin's raises as its one line."""
    with plugin_part(method, "postprocess_datasets"):
        return method.postprocess_datasets()


class _Failed:
    """A `VPRBenchError` (or a plugin's failure, `plugin_failure`) raised in a worker, carried to the main
    process as a plain message."""

    def __init__(self, message: str):
        self.message = message


class _Images:
    """A torch map-style dataset: item i is `method.load(paths[i])`, checked against its identity."""

    def __init__(self, method, paths: Sequence[Path], digests: Sequence[str] | None = None):
        self.method, self.paths = method, list(paths)
        self.digests = list(digests) if digests is not None else None

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, i: int):
        try:
            if self.digests is None:
                return self.method.load(self.paths[i])
            path, expected = self.paths[i], self.digests[i]
            with reads_seen() as seen:
                item = self.method.load(path)
            decoded = seen.get(os.path.abspath(path))
            if decoded is not None:
                return item if decoded == expected else _Failed(changed_message(path, expected, decoded, decoded))
            before = _digest(path)  # the method read the file itself: hashed around a second load
            item = self.method.load(path)
            after = _digest(path)
            if not before == after == expected:
                return _Failed(changed_message(path, expected, before, after))
            return item
        except VPRBenchError as error:
            return _Failed(str(error))
        except (Exception, SystemExit) as error:
            message = plugin_failure(self.method, "load", error, on=f"image {self.paths[i]}")
            if message is None:
                raise
            return _Failed(message)


def _digest(path: Path) -> str:
    from .fsutil import file_sha256

    try:
        return file_sha256(path)
    except OSError as error:
        raise VPRBenchError(f"Cannot read image {path}: {error.strerror or error}.") from None


def changed_message(path: Path, expected: str, before: str, after: str) -> str:
    when = "while vprbench read it" if before != after else "since its identity was taken at the start of this run"
    return (f"Image {path} changed {when} (sha256 {expected[:12]}… expected, {after[:12]}… now): its row is not "
            "described, so no store holds descriptors of other bytes than its key names; the rows already "
            "described are kept. Let whatever is writing the images finish, then run again.")


def batch_named(paths: Sequence) -> str:
    """The images of a batch a plugin failed on, for its message: the first, and how many more."""
    more = f" (and {len(paths) - 1} more in its batch)" if len(paths) > 1 else ""
    return f"image {paths[0]}{more}"


def _as_batch(items: list) -> list:
    return items


def check_batch_size(method) -> int:
    size = getattr(method, "batch_size", 1)
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise VPRBenchError(f"Method {method.name!r}: batch size must be a whole number >= 1, got {size!r}.")
    return int(size)


def _numbers(source: str, rows, n: int) -> np.ndarray:
    """`rows` (an array, a torch tensor on any device, nested lists) as an array of real numbers."""
    torch = sys.modules.get("torch")
    try:
        if torch is not None and isinstance(rows, torch.Tensor):  # with grad, on a GPU, in bfloat16: all fine
            rows = rows.detach().cpu()  # a meta tensor (no data) or a sparse one is refused below, not a traceback
            rows = (rows.float() if rows.is_floating_point() else rows).numpy()
        if isinstance(rows, np.ma.MaskedArray):  # np.asarray drops the mask: its masked entries are missing values
            mask = np.atleast_1d(np.ma.getmaskarray(rows))
            missing = np.flatnonzero(mask.any(axis=tuple(range(1, mask.ndim))))
            if missing.size:
                raise VPRBenchError(f"{source} returned a masked array with masked (missing) entries, first in row "
                                    f"{missing[0]} of {n}: return plain rows with every value filled in.")
        out = np.asarray(rows)
    except (TypeError, ValueError, RuntimeError, NotImplementedError) as error:
        out, reason = None, f" ({error})"
    else:
        reason = f" of {out.dtype} values"
    if out is None or out.dtype.kind not in "biuf":  # complex, text, objects, None: nothing to cast silently
        shown = "None" if rows is None else f"{type(rows).__name__}{reason}"
        raise VPRBenchError(f"{source} returned {shown}; expected a ({n}, dim) array of real numbers (float32).")
    with np.errstate(over="ignore"):  # a float64 beyond float32's range becomes inf, reported below
        return out.astype(np.float32)


def checked(source: str, descriptors, n: int, dim: int | None = None, compare: str | None = None) -> np.ndarray:
    """Rows a method (or its post-processing) hands to the store or the search, as (n, dim)
    finite float32, or an error naming `source` ("Method 'x'"). A method's rows compared by cosine
    (`compare`) must be L2-normalised (or all zero), as the search scores them by inner products;
    no row may be so long that its inner products leave float32's range."""
    out = _numbers(source, descriptors, n)
    if out.ndim != 2 or out.shape[0] != n or out.shape[1] < 1:
        raise VPRBenchError(f"{source} returned shape {out.shape} for {n} images; expected ({n}, dim).")
    if dim is not None and out.shape[1] != dim:
        raise VPRBenchError(f"{source} returned {out.shape[1]}-dimensional descriptors after {dim}-dimensional ones.")
    finite = np.isfinite(out).all(axis=1)
    if not finite.all():  # most often a row divided by its length where that is 0 (a blank image)
        raise VPRBenchError(f"{source} returned non-finite descriptors (NaN, infinity, or beyond float32's range), "
                            f"first in row {np.flatnonzero(~finite)[0]} of {n}: fix it (an image with nothing to "
                            "describe gets an all-zero row: guard a division by a row's length).")
    lengths = np.sqrt(np.einsum("ij,ij->i", out, out, dtype=np.float64))
    if compare == "cosine":
        wrong = np.flatnonzero((lengths >= ZERO_LENGTH) & (np.abs(lengths - 1) > UNIT_TOLERANCE))
        if wrong.size:
            raise VPRBenchError(
                f"{source} returned rows that are not L2-normalised (row {wrong[0]} has length "
                f"{lengths[wrong[0]]:.4g}): "
                "descriptors compared by cosine must have length 1 (or be all zero); normalise them, e.g. with "
                "vprbench.methods.l2_normalise.")
    too_long = np.flatnonzero(lengths > MAX_LENGTH)
    if too_long.size:  # by Cauchy-Schwarz, no two rows within it have an inner product beyond float32's range
        raise VPRBenchError(f"{source} returned rows too long to compare (row {too_long[0]} has length "
                            f"{lengths[too_long[0]]:.3g}: their inner products exceed float32's range); scale them "
                            "down, e.g. L2-normalise them.")
    return out


def _exit_with_parent(run: int, _worker: int) -> None:
    """A loader worker whose run was killed (kill -9) would wait for ever to hand over a batch nobody
    reads (torch's own check never runs then): it leaves as soon as its parent or its run is gone
    (under forkserver its parent is the fork server, which outlives the run)."""
    import threading
    import time

    parent = os.getppid()

    def alive() -> bool:
        if os.getppid() != parent:
            return False
        try:
            os.kill(run, 0)
        except ProcessLookupError:
            return False
        except OSError:  # another user's process: it exists
            pass
        return True

    def watch():
        while alive():
            time.sleep(1)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()


def describe_batches(method, paths: Sequence[Path], *, workers: int = 0, device: str = "cpu",
                     digests: Sequence[str] | None = None) -> Iterator[tuple[int, np.ndarray]]:
    """(offset, descriptors) for consecutive batches of `paths`, in input order; with `digests`
    (the sha256 each image must have), an image whose bytes differ stops the loop before its batch."""
    size = check_batch_size(method)
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 0:
        raise VPRBenchError(f"--workers must be a whole number >= 0, got {workers!r}.")
    if not paths:
        return
    import torch
    from torch.utils.data import DataLoader

    from .features.allocator import keep_freed_memory

    keep_freed_memory()  # each batch's tensors reuse the last one's memory
    batches = -(-len(paths) // size)
    # a generator of its own: the loader draws its workers' seed from it, not from the user's random stream
    loader = DataLoader(_Images(method, paths, digests), batch_size=size, shuffle=False, collate_fn=_as_batch,
                        num_workers=min(int(workers), batches), pin_memory=str(device).startswith("cuda"),
                        worker_init_fn=functools.partial(_exit_with_parent, os.getpid()), generator=torch.Generator())
    with torch.device("cpu"):  # its seed drawn on the CPU, as its generator is, whatever torch.set_default_device says
        loaded = iter(loader)
    offset, dim = 0, None
    for items in loaded:
        for item in items:
            if isinstance(item, _Failed):
                raise VPRBenchError(item.message)
        n = len(items)  # counted before describe, which may pop from its list: else rows shift onto other images
        with plugin_part(method, "describe", on=batch_named(paths[offset:offset + n])):
            described = method.describe(items)
        descriptors = checked(f"Method {method.name!r}", described, n, dim, getattr(method, "compare", "cosine"))
        dim = descriptors.shape[1]
        yield offset, descriptors
        offset += n
