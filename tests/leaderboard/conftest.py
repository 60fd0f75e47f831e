"""Fixtures of the leaderboard tests: synthetic records (synthetic_runs.py), small and read-only disks."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest
from synthetic_runs import FakeMethod, synthetic_ground_truth, synthetic_search, synthetic_spec

from vprbench.datasets import apply_protocol, dataset_manifest, find_protocol, own_protocol
from vprbench.datasets.model import Dataset
from vprbench.evaluation.record import result_record
from vprbench.stages.run import create_stages, track_of


@pytest.fixture
def make_record(tmp_path):
    """make_record(method="hog", dataset="corridor", ...) -> a record dict of the current schema
    (own data, kind="own", with unit="frames" and a radius: a traverse with that tolerance)."""

    def make(method="hog", dataset="corridor", *, k=20, ks=(1, 5, 10, 20), quality=0.5, seed=0, options=None,
             weights=None, kind="benchmark", n_database=None, n_queries=None, root=None, fingerprint=None,
             domain=None, created=None, descriptor_dim=64, protocol=None, search=None, unit=None, radius=None,
             stages=()):
        manifest = dataset_manifest(dataset) if kind == "benchmark" else None
        n_database = n_database or manifest.database_count
        n_queries = n_queries or manifest.query_count
        rule = (manifest.unit, manifest.radius) if manifest else ((unit, radius) if unit else ())  # own: any rule
        gt = synthetic_ground_truth(n_database, n_queries, *rule)
        positives = gt.positives()
        scores, indices, positives = synthetic_search(positives, n_database, k, quality, seed)
        images = Path(root) if root else tmp_path / "no-images" / dataset
        data = Dataset(dataset, [images / f"db{i}.jpg" for i in range(n_database)],
                       [images / f"q{i}.jpg" for i in range(n_queries)], gt,
                       domain=domain or (manifest.domain if manifest else "custom"), root=images,
                       layout="vpr-bench" if kind == "benchmark" else "own", kind=kind)
        # as load_dataset does: the manifest's protocol (default or named), or the folder's own
        data = apply_protocol(data, find_protocol(manifest, protocol)) if manifest else \
            dataclasses.replace(data, protocol=own_protocol(data))
        fake = FakeMethod(method, options or {}, weights or {"source": "none"})
        spec = synthetic_spec(method, options or {}, weights or {}, data, ks, search or {}, stages)
        record = result_record(
            spec=spec, method=fake, track=track_of(create_stages(spec)),
            fingerprint={"method": method, **(options or {})}, dataset=data,
            dataset_key=fingerprint or f"fp-{dataset}-{n_database}", ks=ks, scores=scores, indices=indices,
            positives=positives, descriptor_dim=descriptor_dim, computed={"database": n_database, "queries": n_queries},
            timings={"fit_s": 0.0, "database_s": 1.0, "queries_s": 1.0, "search_s": 0.01, "total_s": 2.0})
        if created:
            record["created"] = created
            record["run_id"] = f"{re.sub('[^0-9A-Za-z]', '', created)}-{re.sub('[^0-9A-Za-z]', '_', method)}-{seed}"
        return record

    return make


def _mount(*args) -> bool:
    import subprocess

    return subprocess.run(["mount", *args], capture_output=True).returncode == 0


@pytest.fixture
def small_disk(tmp_path):
    """small_disk(kib) -> a folder on a tmpfs of that size (a full disk on demand); skipped where
    mounting is not allowed."""
    import subprocess

    mounted = []

    def make(kib: int) -> Path:
        folder = tmp_path / f"disk-{len(mounted)}"
        folder.mkdir()
        if not _mount("-t", "tmpfs", "-o", f"size={kib}k", "tmpfs", str(folder)):
            pytest.skip("cannot mount a small tmpfs here (needs root and mount permission)")
        mounted.append(folder)
        return folder

    yield make
    for folder in mounted:
        subprocess.run(["umount", "-l", str(folder)], capture_output=True)


@pytest.fixture
def read_only(tmp_path):
    """read_only(folder) -> the same folder mounted read-only (we run as root, so chmod would not
    stop a write); skipped where bind mounts are not allowed."""
    import subprocess

    mounted = []

    def make(folder: Path) -> Path:
        view = tmp_path / f"ro-{len(mounted)}"
        view.mkdir()
        if not _mount("--bind", str(folder), str(view)):
            pytest.skip("cannot bind-mount here (needs root and mount permission)")
        mounted.append(view)
        if not _mount("-o", "remount,bind,ro", str(view)):
            pytest.skip("cannot remount read-only here")
        return view

    yield make
    for view in mounted:
        subprocess.run(["umount", "-l", str(view)], capture_output=True)
