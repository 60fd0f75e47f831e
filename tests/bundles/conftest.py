"""Real runs on the real Corridor (hog, two rows) in a results store, and bundles rebuilt with edits."""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tarfile
from pathlib import Path

import pytest

from vprbench.bundles.export import MANIFEST
from vprbench.evaluation import evaluate, read_results, save_result
from vprbench.spec import RunSettings, resolve_spec


@pytest.fixture(scope="session")
def corridor_store(shared_data, tmp_path_factory) -> Path:
    """A cache whose results store holds two real hog runs on Corridor (two rows: default and resized)."""
    cache = tmp_path_factory.mktemp("contributor-store")
    settings = RunSettings(cache_dir=cache, data_dir=shared_data, workers=0)
    for options in ({}, {"resize": [96, 128]}):
        spec = resolve_spec("hog", "corridor", options=options, data_dir=shared_data, cache_dir=cache)
        save_result(evaluate(spec, settings), cache)
    return cache


@pytest.fixture
def store(corridor_store, tmp_path) -> Path:
    """A private copy of the store (a test may change it)."""
    copy = tmp_path / "store"
    shutil.copytree(corridor_store / "results", copy / "results")
    return copy


@pytest.fixture
def records(store):
    return read_results(store)


def read_bundle(path: Path) -> dict[str, bytes]:
    with tarfile.open(path) as archive:
        return {m.name: archive.extractfile(m).read() for m in archive.getmembers()}


def write_bundle(path: Path, members: dict[str, bytes], *, resum: bool = True) -> Path:
    """Write `members` as a bundle; with `resum`, the manifest's sums are made to match (a careful forger)."""
    members = dict(members)
    if resum:
        manifest = json.loads(members[MANIFEST])
        manifest["files"] = {n: {"sha256": hashlib.sha256(d).hexdigest(), "bytes": len(d)}
                             for n, d in members.items() if n != MANIFEST}
        members[MANIFEST] = json.dumps(manifest).encode()
    with tarfile.open(path, "w:gz") as archive:
        for name, data in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))
    return path


def record_names(members) -> list[str]:
    return sorted(n for n in members if n.endswith(".json") and n.count("/") == 2)
