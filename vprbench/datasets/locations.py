"""Where each dataset lives: the data root's default folder, or a copy registered with `import`
(`datasets.json` in the data root, written by storage.import_dataset); and the commands that get or
check a dataset there, naming that data root. Below the layout readers, whose errors give this advice.
"""
from __future__ import annotations

import json
import shlex
from pathlib import Path

from ..errors import VPRBenchError
from ..fsutil import atomic_write
from .manifest import DatasetManifest, data_root, default_data_root

REGISTRY = "datasets.json"


def registry_path(data_dir=None) -> Path:
    return data_root(data_dir) / REGISTRY


def read_registry(data_dir=None) -> dict[str, str]:
    path = registry_path(data_dir)
    if not path.is_file():
        return {}
    try:
        entries = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(entries, dict):
            raise ValueError("expected a JSON object of name -> path")
        for name, where in entries.items():  # import writes absolute paths; anything else was not written by it
            if not isinstance(where, str) or not Path(where).is_absolute():
                raise ValueError(f"the entry {name!r} is {where!r}, not the absolute path of a folder")
    except (OSError, ValueError, RecursionError) as error:
        raise VPRBenchError(f"Cannot read the dataset registry {path}: {error}. Fix or delete it, then import again.") from None
    return entries


def write_registry(entries: dict[str, str], data_dir=None) -> Path:
    """Write atomically, so a crash or a full disk never leaves half a registry."""
    return atomic_write(registry_path(data_dir), json.dumps(dict(sorted(entries.items())), indent=2))


def dataset_location(manifest: DatasetManifest, data_dir=None) -> Path:
    """The imported copy if one is registered, else <data root>/<manifest directory>."""
    registered = read_registry(data_dir).get(manifest.name)
    return Path(registered) if registered else data_root(data_dir) / manifest.directory


def data_root_flag(base: Path) -> str:
    """The `--data-dir` a printed command needs to act on the data root `base` (none for the default
    one): downloads and imports go to, and are looked up in, one data root."""
    return "" if base == default_data_root() else f" --data-dir {shlex.quote(str(base))}"


def how_to_get(manifest: DatasetManifest, data_dir=None) -> str:
    """What to do to have the dataset where the data root `data_dir` (None: the default) looks for it
    (its folder there, or the place of the copy imported into it), the printed commands naming that
    data root. Manifests' instructions say how to get the data, never where it goes: that is said
    here, once."""
    root, named = dataset_location(manifest, data_dir), data_root_flag(data_root(data_dir))
    if manifest.download:
        return f"Run 'vprbench datasets download {manifest.name}{named}' to fetch it into {root}."
    text = manifest.instructions.strip() or f"Get it from {manifest.source or 'its authors'}."
    return (f"{text} Place it at {root}, or run 'vprbench datasets import {manifest.name} PATH{named}' on a copy "
            "elsewhere.")


def verify_command(manifest: DatasetManifest, root: Path, data_dir=None) -> str | None:
    """The command that checks the copy at `root`, naming the data root `data_dir` as the user did;
    None when that data root looks for the dataset elsewhere (`root` is a folder being imported): its
    command would check another copy."""
    if Path(root) != dataset_location(manifest, data_dir):
        return None
    return f"vprbench datasets verify {manifest.name}{data_root_flag(data_root(data_dir))}"
