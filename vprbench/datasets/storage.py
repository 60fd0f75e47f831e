"""A copy of a dataset: importing one, and checking one against its manifest (counts, images).

`vprbench datasets import NAME PATH` records NAME -> PATH in `datasets.json` in the data
root (see locations.py), after the copy at PATH has been read completely (layout, images, ground
truth), so a failed import leaves nothing behind. The registry is read, changed and rewritten
(atomically) under one lock, `datasets.json.lock` beside it, so imports running at once all stay
recorded.
"""
from __future__ import annotations

import warnings
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import lock
from ..paths import resolved
from .layouts import candidates, detect_layout, missing_paths, read_layout
from .locations import data_root_flag, how_to_get, read_registry, registry_path, verify_command, write_registry
from .manifest import DatasetManifest, data_root, dataset_manifest, is_default_data_root
from .model import Dataset


def nearest_existing(path: Path) -> str:
    """The deepest existing folder on the way to `path`, with the names in it closest to the
    first missing part (so a typo in --data-dir shows)."""
    import difflib

    missing = Path(path).absolute()
    while not missing.parent.exists() and missing.parent != missing:
        missing = missing.parent
    try:
        folders = [p.name for p in missing.parent.iterdir() if p.is_dir()]
    except OSError:
        folders = []
    close = difflib.get_close_matches(missing.name, folders, n=3, cutoff=0.6)
    return str(missing.parent) + (f" (which holds {', '.join(close)})" if close else "")


def is_dataset_folder(folder: Path, manifest: DatasetManifest) -> bool:
    """Whether `folder` itself holds the dataset in one of its layouts."""
    return folder.is_dir() and any(not missing_paths(folder, c) for c in candidates(manifest))


def missing_dataset_message(manifest: DatasetManifest, root: Path, data_dir=None) -> str:
    """Why `manifest`'s dataset is not found at `root` and what to do: a data root that is the
    dataset folder itself, the closest existing path, how to get the data."""
    name, base = manifest.name, data_root(data_dir)
    if read_registry(data_dir).get(name):
        # the registry read is this data root's: an import into the default one would not be seen here
        named = data_root_flag(base)
        return (f"Dataset {name!r} was imported from {root}, which no longer exists (closest existing folder: "
                f"{nearest_existing(root)}). Import it again with 'vprbench datasets import {name} PATH{named}'.")
    if is_dataset_folder(base, manifest) or base.name == manifest.directory:
        return (f"The data root {base} is the {name!r} dataset folder itself; the data root is the folder that "
                f"holds the datasets: use the folder above, --data-dir {base.parent}.")
    where = f"; closest existing path: {nearest_existing(root)}"
    if manifest.download and is_default_data_root(data_dir):
        get = f"Run 'vprbench datasets download {name}' (evaluate fetches it by itself into the default data root)."
    elif manifest.download:
        get = (f"To download it there, add --download to evaluate or run 'vprbench datasets download {name} "
               f"--data-dir {base}'.")
    else:
        get = how_to_get(manifest, data_dir)
    return f"Dataset {name!r} is not in the data root {base}: looked for {root}{where}. {get}"


def check_counts(dataset: Dataset, manifest: DatasetManifest, strict: bool, data_dir=None) -> list[str]:
    """Messages for counts that differ from the manifest; raises instead when strict, or when the
    ground truth names images by position (then the counts must be the manifest's). The counts are
    those of the layout the copy is in (an alternative layout may give its own). `data_dir`: the data
    root the copy is read from (or imported into), for the advice."""
    messages, manifest = [], detect_layout(dataset.root, manifest)
    for split, expected, found in (
        ("database", manifest.database_count, len(dataset.database)),
        ("query", manifest.query_count, len(dataset.queries)),
    ):
        if expected is not None and expected != found:
            messages.append(f"Dataset {manifest.name!r}: {found} {split} images at {dataset.root}, the manifest expects {expected}.")
    expected = manifest.database_count
    if by_position(dataset) and expected is not None and expected != len(dataset.database):
        command = verify_command(manifest, dataset.root, data_dir)
        raise VPRBenchError(" ".join(messages) + f" {BY_POSITION} use a complete copy"
                            + (f" ('{command}' lists what differs)." if command else "."))
    if messages and strict:
        raise VPRBenchError(" ".join(messages) + " (--strict)")
    for message in messages:
        warnings.warn(message, stacklevel=3)
    return messages


#: why a database count that differs is no warning where the ground truth lists positives by index
BY_POSITION = ("Its ground truth names database images by their position in the sorted list, so with an image "
               "more or fewer every later index would point at another image:")


def by_position(dataset: Dataset) -> bool:
    """The ground truth is lists of database indices (VPR-Bench style), not positions in space. (Its
    rows of queries are checked against the query images as it is read.)"""
    return dataset.ground_truth.positive_lists is not None


def absent_or_empty(paths: list[Path]) -> str:
    """'' when every listed image is a file with bytes, else what is wrong, with the first few."""
    absent, empty = [], []
    for path in paths:
        try:
            if path.stat().st_size == 0 or not path.is_file():
                empty.append(path)
        except OSError:  # missing, or a link to nothing
            absent.append(path)
    return "; ".join(f"{len(found)} listed image(s) {what}, e.g. {', '.join(str(p) for p in found[:5])}"
                     for found, what in ((absent, "are missing"), (empty, "are empty or no file")) if found)


def import_dataset(name: str, path: str | Path, data_dir=None, strict: bool = False) -> Dataset:
    """Register an existing copy of dataset `name` at `path`, after checking it reads completely."""
    manifest = dataset_manifest(name)
    root = resolved(path, f"The folder to import {name!r} from")
    if not root.is_dir():
        what = "is a file, not a folder" if root.exists() else f"does not exist; closest existing path: {nearest_existing(root)}"
        raise VPRBenchError(f"Cannot import {name!r}: {root} {what}. Give the folder holding your copy of {name}.")
    dataset = read_layout(root, manifest, data_dir)  # raises, naming what is missing, before anything is written
    check_counts(dataset, manifest, strict, data_dir)  # first: an image more or fewer is named as such
    dataset.positives  # ground truth must match the images  # noqa: B018
    bad = absent_or_empty(dataset.database + dataset.queries)  # a stat each: cheap at any benchmark's size
    if bad:
        raise VPRBenchError(f"Cannot import {name!r}: {bad}; get those images again, then import it.")
    registry = registry_path(data_dir)
    # held for the moment of a read and a write; 120 s is ample even on a slow network disk
    with lock(registry.with_name(registry.name + ".lock"), timeout=120.0, what=f"the dataset registry {registry}",
              announce=False):
        entries = read_registry(data_dir)
        entries[name] = str(root)
        write_registry(entries, data_dir)
    return dataset
