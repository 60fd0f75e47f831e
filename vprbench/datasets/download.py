"""Fetching a dataset whose manifest names a stable direct source (pooch, sha256-checked)."""
from __future__ import annotations

import contextlib
from importlib.resources import files
from pathlib import Path

from ..errors import VPRBenchError, network_reason, url_host
from ..fsutil import lock, remove_stale
from .locations import data_root_flag, how_to_get
from .manifest import DatasetManifest, data_root


def read_registry(name: str) -> dict[str, str]:
    """A sha256 registry shipped beside the manifests: lines '<relative path> <sha256>'."""
    text = (files("vprbench.manifests") / "datasets" / name).read_text(encoding="utf-8")
    return dict(line.split() for line in text.splitlines() if line.strip() and not line.startswith("#"))


def download(manifest: DatasetManifest, root: Path, progress: bool = True, data_dir=None) -> Path:
    """Download into root (via root.partial, renamed when every file checks out), the dataset's place
    in the data root `data_dir` (whose --data-dir the advice on a failure names). Downloads of one
    dataset into one data root take turns: the one that waited finds the first one's copy and keeps it
    (two at once into one partial folder had one rename it away while the other still wrote there)."""
    if not manifest.download:
        raise VPRBenchError(f"Dataset {manifest.name!r} has no direct download. {how_to_get(manifest, data_dir)}")
    with lock(root.with_name(f".{root.name}.download.lock"), what=f"the download of {manifest.name!r} into {root}"):
        if not root.exists():
            _fetch(manifest, root, data_dir)
    return root


def _fetch(manifest: DatasetManifest, root: Path, data_dir=None) -> None:
    import pooch

    partial = root.with_name(root.name + ".partial")
    fetcher = pooch.create(
        path=partial,
        base_url=manifest.download["base_url"],
        registry={k: f"sha256:{v}" for k, v in read_registry(manifest.download["registry"]).items()},
    )
    for relative in fetcher.registry:
        try:
            fetcher.fetch(relative, progressbar=False)
        except Exception as error:  # network or checksum failure: keep partial for resuming
            with contextlib.suppress(OSError):
                partial.rmdir()  # nothing fetched (the folder is empty): none left behind
            kept = f"Files fetched so far stay in {partial}; rerun to resume." if partial.exists() else \
                "Check the network and rerun."
            raise VPRBenchError(
                f"Downloading {manifest.name!r} from {url_host(manifest.download['base_url'])} failed at {relative}: "
                f"{network_reason(error).rstrip('.')}. {kept} Or get the files yourself and run "
                f"'vprbench datasets import {manifest.name} PATH{data_root_flag(data_root(data_dir))}'."
            ) from None
    # pooch streams each file into a tmp* file beside it: a killed download's would be renamed into the
    # dataset for good (no live one is writing: the lock)
    remove_stale((p for p in partial.rglob("tmp*") if p.relative_to(partial).as_posix() not in fetcher.registry),
                 age_s=0)
    partial.rename(root)
