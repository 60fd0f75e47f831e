"""Where a run's parts came from (`method_provenance`) and what it ran on (`environment`): the
provenance and hardware sections of a result record (record.py)."""
from __future__ import annotations

import json
import os
import platform
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import VPRBenchError


def method_provenance(method, dataset=None, cache_dir=None) -> dict:
    """`method.provenance()`, completed: a method that does not say where its weights came from
    is 'undeclared' (never official); a method that fits on the database says so, and so does
    one whose post-processor (e.g. PCA-whitening) is fitted on the database's descriptors.

    Summaries for tables: `learnt` names every fitted part (vocabulary, pca, ...), so a method
    with learnt parts is never "nothing learnt" even when its weights source is "none";
    `fitted_on_evaluated_database` is true when any part was fitted on the evaluated database
    (transductive), null when a part does not say, else false. A part fitted on images the method
    names by content (`fitted_image_digests()`, sha256 of each file) is transductive when any of
    them is an image of the evaluated `dataset`, whatever the method says."""
    from ..methods import Method

    from ..loader import plugin_part, postprocess_datasets_of, postprocessor_of

    with plugin_part(method, "provenance"):
        own = method.provenance() or {}
    if not isinstance(own, dict):
        raise VPRBenchError(f"Method {method.name!r}: provenance() must return a dict such as "
                            f"{{\"weights\": {{\"source\": \"none\"}}}}, got {type(own).__name__}.")
    own = json.loads(json.dumps(own, default=str))  # the record is JSON: a value that is not is kept as its text
    found = {k: dict(v) if isinstance(v, dict) else v for k, v in own.items()}
    declared = type(method).provenance is not Method.provenance
    found.setdefault("weights", {"source": "none" if declared else "undeclared"})
    if method.needs_fit:
        found.setdefault("vocabulary", {"source": "map", "fitted_on": "the evaluated database"})
        found["vocabulary"].setdefault("fitted_on_evaluated_database", True)
    post = postprocessor_of(method)
    if post is not None and not any(k in found for k in ("pca", "postprocessor")):
        stacked = postprocess_datasets_of(method)
        found["postprocessor"] = {"source": "fitted", "fitted_on_evaluated_database": True, "fitted_on": (
            f"the databases of {', '.join(map(str, stacked))} stacked" if stacked else "the evaluated database's descriptors")}
    parts = {k: v for k, v in found.items() if isinstance(v, dict) and "fitted_on_evaluated_database" in v}
    with plugin_part(method, "fitted_image_digests"):
        fitted_images = getattr(method, "fitted_image_digests", lambda: {})()  # part -> set of sha256
    if not isinstance(fitted_images, dict) or not all(isinstance(v, (set, frozenset, list, tuple))
                                                       for v in fitted_images.values()):
        raise VPRBenchError(f"Method {method.name!r}: fitted_image_digests() must return a dict of part -> set of "
                            f"sha256, such as {{\"vocabulary\": {{\"<sha256>\"}}}}, got {type(fitted_images).__name__}.")
    if fitted_images and dataset is not None:
        evaluated = {d for split in dataset.image_digests(cache_dir).values() for d in split}
        for part, digests in fitted_images.items():
            shared = len(set(digests) & evaluated)
            if shared and part in parts:
                parts[part].update(fitted_on_evaluated_database=True, evaluated_images_fitted_on=shared)
    for part in parts.values():  # a file says what it is by its bytes when nothing else is known
        if "fitted_on" not in part and part.get("sha256"):
            part["fitted_on"] = f"{part.get('released_as') or 'file'} sha256:{part['sha256']}"
    found["learnt"] = sorted(parts)
    leaks = [v["fitted_on_evaluated_database"] for v in parts.values()]
    found["fitted_on_evaluated_database"] = True if True in leaks else (None if None in leaks else False)
    return found


def environment() -> dict:
    import faiss
    import h5py
    import torch

    from ..gemm import library

    versions = {"vprbench": __version__, "python": platform.python_version(), "numpy": np.__version__,
                "torch": torch.__version__, "faiss": faiss.__version__, "h5py": h5py.__version__,
                "git": _git_commit()}
    hardware = {"platform": platform.platform(), "machine": platform.machine(), "cpu": _cpu_name(),
                "cpu_count": os.cpu_count(), "memory_gib": _memory_gib(),
                "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                # what computed fp32 products on the CPU: its speed (and their last bits) depend on it
                "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu_products": library()}
    return {"versions": versions, "hardware": hardware}


def _git_commit() -> str | None:
    """The commit of a vprbench source checkout (None for an installed wheel)."""
    head = Path(__file__).resolve().parents[2] / ".git"
    try:
        if head.is_file():  # a worktree: "gitdir: <path>"
            head = Path(head.read_text().split(":", 1)[1].strip())
        ref = (head / "HEAD").read_text().strip()
        if ref.startswith("ref: "):
            name = ref[5:]
            common = head / "commondir"
            root = (head / common.read_text().strip()).resolve() if common.is_file() else head
            for folder in (head, root):
                if (folder / name).is_file():
                    return (folder / name).read_text().strip()
            packed = root / "packed-refs"
            lines = packed.read_text().splitlines() if packed.is_file() else []
            return next((line.split()[0] for line in lines if line.endswith(" " + name)), None)
        return ref
    except (OSError, IndexError):
        return None


def _cpu_name() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or None


def memory_bytes() -> int | None:
    """This machine's physical memory, None where the system does not say."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def _memory_gib() -> float | None:
    memory = memory_bytes()
    return None if memory is None else round(memory / 2**30, 1)
