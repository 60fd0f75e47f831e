"""A post-processor fitted on several benchmarks' databases stacked, as the AnyLoc authors fitted
the PCA of their -PCA rows (scripts/joint_pca_project.py: a domain's database descriptors stacked,
PCA fitted on them, then applied to each dataset's database and queries). A method asks for it with
`postprocess_datasets()`; each other dataset's database is described as its own evaluation would
describe it, so the stores serve both."""
from __future__ import annotations

import hashlib

import numpy as np

from ..errors import VPRBenchError
from ..loader import postprocess_datasets_of, postprocessor_of
from ..methods.attributes import use_dataset
from .extract import describe_splits
from .identity import protocol_of
from .postprocess import overrides_postprocess


class JointRows:
    """Row sources read as one, in order: what a joint post-processor is fitted on. Its content key
    names every part's; its folder (where the fitted state is kept) is the first part's, so each
    dataset of the stack loads the one fit. With a part of unknown content it keeps no state."""

    def __init__(self, parts: list):
        if not parts or len({(p.dim, np.dtype(p.dtype)) for p in parts}) > 1:
            found = ", ".join(f"{p.dim} x {np.dtype(p.dtype)}" for p in parts) or "none"
            raise VPRBenchError(f"Descriptors stacked for one fit must share their dimension and dtype, got {found}.")
        self.parts = parts
        self.starts = np.cumsum([0, *(int(p.row_count) for p in parts)])
        self.row_count, self.dim, self.dtype = int(self.starts[-1]), int(parts[0].dim), np.dtype(parts[0].dtype)
        known = all(callable(getattr(p, "content_key", None)) for p in parts)
        self.folder = parts[0].folder if known else None

    def content_key(self) -> str:
        keys = "|".join(f"{p.row_count}:{p.content_key()}" for p in self.parts)
        return hashlib.sha256(keys.encode()).hexdigest()[:16]

    def read_rows(self, start: int, stop: int) -> np.ndarray:
        i = int(np.searchsorted(self.starts, start, side="right")) - 1
        if start < stop and stop <= self.starts[i + 1]:  # within one part: its fresh rows, not a second copy
            return self.parts[i].read_rows(start - int(self.starts[i]), stop - int(self.starts[i]))
        out = np.empty((stop - start, self.dim), dtype=np.float32)
        for part, first in zip(self.parts, self.starts):
            lo, hi = max(start, int(first)), min(stop, int(first) + part.row_count)
            if lo < hi:
                out[lo - start:hi - start] = part.read_rows(lo - first, hi - first)
        return out

    def read_rows_at(self, indices) -> np.ndarray:
        indices = np.asarray(indices, dtype=np.int64)
        which = np.searchsorted(self.starts, indices, side="right") - 1
        out = np.empty((len(indices), self.dim), dtype=np.float32)
        for i, part in enumerate(self.parts):
            mine = which == i
            if mine.any():
                out[mine] = part.read_rows_at(indices[mine] - self.starts[i])
        return out


def stacked(method: str, names) -> str:
    """The start of what is said of a method fitting on several databases."""
    return f"Method {method!r} fits its post-processor on the databases of {', '.join(names)} stacked"


def joint_members(method, dataset, settings, ranks) -> list | None:
    """The datasets (the evaluated `dataset` among them, in the method's order) whose databases the
    method's post-processor is fitted on, loaded and checked before any image is described; None
    when that is the evaluated database alone."""
    from ..datasets import load_dataset

    names = postprocess_datasets_of(method)
    if names is None:
        return None
    if (not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names)
            or len(set(names)) != len(names) or dataset.name not in names):
        raise VPRBenchError(f"Method {method.name!r}: postprocess_datasets() must return distinct benchmark names "
                            f"among them the evaluated {dataset.name!r}, got {names!r}; fix the method.")
    if list(names) == [dataset.name]:
        return None
    # else the stack would be described, and the record name it, for a fit never made
    if (getattr(method, "compare", "cosine") != "cosine" or overrides_postprocess(method)
            or postprocessor_of(method) is None):
        raise VPRBenchError(f"Method {method.name!r}: postprocess_datasets() names {', '.join(names)} to fit its "
                            "postprocessor() on, but it fits none there (no postprocessor(), a whole-matrix "
                            "postprocess() or a comparison other than cosine sees the evaluated database alone); "
                            "fix the method.")

    def load(name):
        try:
            return load_dataset(name, settings.data_dir, strict=settings.strict, fetch=settings.download,
                                cache_dir=settings.cache_dir)
        except VPRBenchError as error:  # the user named another dataset: say why this one is read
            raise VPRBenchError(f"{stacked(method.name, names)}, so evaluating {dataset.name} needs {name}: "
                                f"{error}") from None

    members = [dataset if name == dataset.name else ranks.on_zero(lambda name=name: load(name)) for name in names]
    try:
        for member in members:
            use_dataset(method, member.name)
            if method.needs_fit:
                raise VPRBenchError(
                    f"{stacked(method.name, names)}, but it would fit a vocabulary on {member.name}'s own database "
                    "(none shared by all of them is ready), so their descriptors would not be comparable: give it one "
                    "vocabulary for all (a domain's: "
                    "`vprbench vocabulary fit --domain DOMAIN --method ...`), or fit the post-processor on the "
                    "evaluated database alone.")
    finally:
        use_dataset(method, dataset.name)
    return members


def describe_members(spec, settings, method, dataset, members: list, described, *, workers: int, ranks,
                     progress) -> tuple[JointRows | None, dict]:
    """(the members' database rows stacked, on rank 0; what each member is and what was computed now)
    once `dataset` is `described`: every other member's database described as its own evaluation
    would (keyed by the spec's options, with that dataset's settings: AnyLoc's resize)."""
    parts, info = [], {}
    try:
        for member in members:
            if member.name == dataset.name:
                part, computed = described.stores and described.stores["database"], described.computed["database"]
            else:
                use_dataset(method, member.name)
                done = describe_splits(
                    method, {"database": member.database}, root=member.root, label=member.name,
                    digests=member.image_digests(settings.cache_dir), names=member.image_names(),
                    cache_dir=settings.cache_dir, store_dtype=spec.store_dtype, workers=workers,
                    lock_timeout=settings.lock_timeout, ranks=ranks, progress=progress, settings=spec.options)
                part, computed = done.stores and done.stores["database"], done.computed["database"]
            parts.append(part)
            info[member.name] = {**member_identity(member, settings.cache_dir), "computed": int(computed)}
    finally:
        use_dataset(method, dataset.name)
    return (JointRows(parts) if ranks.rank == 0 else None), info


def member_identity(member, cache_dir=None) -> dict:
    """What a stacked database is, as the record names it: its protocol and its images' content."""
    return {"protocol": protocol_of(member)["id"], "database_images": len(member.database),
            "images": member.images_fingerprint(cache_dir)}


def stack_identity(method, spec, settings) -> dict | None:
    """`member_identity` of each dataset the method (made for `spec`'s dataset) fits its post-processor
    on, as found now (never downloaded); None when that is the evaluated database alone."""
    from ..datasets import load_dataset

    names = postprocess_datasets_of(method)
    if not names or list(names) == [spec.dataset.name]:
        return None
    return {name: member_identity(load_dataset(
        name, settings.data_dir, fetch=False, protocol=spec.dataset.protocol if name == spec.dataset.name else None,
        cache_dir=settings.cache_dir), settings.cache_dir) for name in names}


def stack_as_recorded(record: dict, identities: dict | None) -> bool:
    """Whether a stored record's post-processor was fitted on the databases `identities` name, as they
    are now (`stack_identity`): the spec names the stack, not its content, so an edited member's
    database makes another fit. True when nothing is stacked."""
    if identities is None:
        return True
    found = (record.get("context") or {}).get("postprocess_datasets")
    if not isinstance(found, dict) or set(found) != set(identities):
        return False
    return all(_fitted_on(found[name]) == _fitted_on(identity) for name, identity in identities.items())


def _fitted_on(entry) -> tuple:
    """What of a member's identity its database rows depend on."""
    entry = entry if isinstance(entry, dict) else {}
    images = entry.get("images") if isinstance(entry.get("images"), dict) else {}
    return entry.get("protocol"), entry.get("database_images"), images.get("database")
