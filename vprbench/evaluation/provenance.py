"""Where a run's parts came from (`method_provenance`, `origins`) and what it ran on (`environment`): the
provenance, software and hardware sections of a result record (record.py)."""
from __future__ import annotations

import json
import os
import platform
import sys
from importlib import metadata
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
    from ..loader import plugin_part, postprocess_datasets_of, postprocessor_of

    with plugin_part(method, "provenance"):
        own = method.provenance() or {}
    if not isinstance(own, dict):
        raise VPRBenchError(f"Method {method.name!r}: provenance() must return a dict such as "
                            f"{{\"weights\": {{\"source\": \"none\"}}}}, got {type(own).__name__}.")
    own = json.loads(json.dumps(own, default=str))  # the record is JSON: a value that is not is kept as its text
    found = {k: dict(v) if isinstance(v, dict) else v for k, v in own.items()}
    # weights a method does not name are undeclared, also when it says other things (a vocabulary): "none" is a
    # claim (nothing learnt, the official row) the method must make itself
    found.setdefault("weights", {"source": "undeclared"})
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
                "git": _git_commit(), **_library_versions()}
    hardware = {"platform": platform.platform(), "machine": platform.machine(), "cpu": _cpu_name(),
                "cpu_count": os.cpu_count(), "memory_gib": _memory_gib(),
                "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
                # what computed fp32 products on the CPU: its speed (and their last bits) depend on it
                "cpu_capability": torch.backends.cpu.get_cpu_capability(), "cpu_products": library()}
    return {"versions": versions, "hardware": hardware}


#: libraries that decide the numbers when a run uses them: import name -> the key its version has in the record
LIBRARIES = {"timm": "timm", "torchvision": "torchvision", "cv2": "opencv", "kornia": "kornia",
             "sklearn": "scikit-learn", "scipy": "scipy", "PIL": "pillow"}


def _library_versions() -> dict:
    """The version of each of LIBRARIES this process imported (one it did not import took no part in the numbers:
    left out), read from its installed distribution's metadata; the module's own __version__ if none is found."""
    found = {}
    for module, key in LIBRARIES.items():
        if module in sys.modules:
            _, version = distribution_of(module)
            found[key] = version or getattr(sys.modules[module], "__version__", None)
    return found


def origins(method_name: str, stage_names) -> dict:
    """Who provides the run's method and each of its stages: the top-level module of what is registered
    under the name, and the installed distribution (name and version) holding that module; both null for
    code from a script or notebook, which no distribution holds."""
    from ..methods.registry import available_methods
    from ..registration import source_of
    from ..stages.registry import available_stages

    def origin(name, entry) -> dict:
        module = source_of(entry.target) if entry else None
        distribution, version = distribution_of(module) if module else (None, None)
        return {"name": name, "module": module, "distribution": distribution, "version": version}

    stages = available_stages() if stage_names else {}  # a run without stages loads no stage plugin
    return {"method": origin(method_name, available_methods().get(method_name)),
            "stages": [origin(name, stages.get(name)) for name in stage_names]}


#: top-level module -> distributions, read once per process (reading every distribution's file list takes
#: 0.3 to 1 s) and again for a module it lacks, once (a plugin installed since, as in a notebook; a module
#: of one's own that no distribution holds is not looked for at every record)
_top_levels: dict[str, list[str]] = {}
_looked_for: set[str] = set()


def distribution_of(module: str) -> tuple[str | None, str | None]:
    """The installed distribution holding top-level `module`, and its version; (None, None) when none does.
    Several (a namespace package): their names and versions, comma-separated."""
    global _top_levels
    if module not in _top_levels and module not in _looked_for and module != "__main__":  # __main__: a script's
        _top_levels = metadata.packages_distributions()
        _looked_for.add(module)
    listed = []
    for name in sorted(set(_top_levels.get(module, []))):
        try:
            listed.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:  # uninstalled since it was listed
            pass
    if not listed:
        return None, None
    return ", ".join(name for name, _ in listed), ", ".join(version for _, version in listed)


def _read(path: Path) -> str:
    """A git file's text in UTF-8 whatever the locale (a path in it keeps its undecodable bytes)."""
    return path.read_text(encoding="utf-8", errors="surrogateescape")


def _git_commit() -> str | None:
    """The commit of a vprbench source checkout (None for an installed wheel)."""
    head = Path(__file__).resolve().parents[2] / ".git"
    try:
        if head.is_file():  # a worktree: "gitdir: <path>"
            head = Path(_read(head).split(":", 1)[1].strip())
        ref = _read(head / "HEAD").strip()
        if ref.startswith("ref: "):
            name = ref[5:]
            common = head / "commondir"
            root = (head / _read(common).strip()).resolve() if common.is_file() else head
            for folder in (head, root):
                if (folder / name).is_file():
                    return _read(folder / name).strip()
            packed = root / "packed-refs"
            lines = _read(packed).splitlines() if packed.is_file() else []
            return next((line.split()[0] for line in lines if line.endswith(" " + name)), None)
        return ref
    except (OSError, IndexError):
        return None


def _cpu_name() -> str | None:
    try:
        for line in Path("/proc/cpuinfo").read_text(encoding="utf-8", errors="replace").splitlines():
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
