"""What a run was computed on, as its record says it: the protocol (named, hashed), the kind of
dataset (a benchmark or a folder of one's own) and the content fingerprints of its data."""
from __future__ import annotations

from ..hashing import canonical_hash


def provisional_protocol(name: str, database: int, queries: int, unit: str, radius) -> dict:
    """For a dataset that carries no protocol (one built by hand, outside `load_dataset`): what
    defines it, marked provisional. The leaderboard puts such runs in no benchmark's cell."""
    defining = {"dataset": name, "database": int(database), "queries": int(queries), "unit": unit,
                "radius": None if radius is None else float(radius)}
    return {"name": "provisional", "id": f"{name}:provisional", "hash": canonical_hash(defining), "provisional": True,
            **defining}


def protocol_of(dataset) -> dict:
    """The evaluated dataset's protocol (datasets/protocol.py), else the provisional one."""
    found = getattr(dataset, "protocol", None)
    if found:
        return dict(found)
    gt = dataset.ground_truth
    return provisional_protocol(dataset.name, len(dataset.database), len(dataset.queries), gt.unit, gt.radius)


def check_loaded_protocol(dataset, found: dict, protocol) -> None:
    """A `protocol` asked of a Dataset already loaded (its protocol `found`, `protocol_of`) must be the
    one it was loaded under: the spec names, and the run computes, the loaded one, so another was
    dropped unsaid (`spec_for(method, load_dataset("nordland"), protocol="tolerance-10")` ran vpr-bench)."""
    from ..datasets import dataset_manifests, find_protocol
    from ..datasets.protocol import DEFAULT
    from ..errors import VPRBenchError
    from ..text import shortened

    if protocol is None:
        return
    manifest = dataset_manifests().get(dataset.name)
    if found["name"] == "own" or found.get("provisional") or manifest is None:  # it has one protocol
        if protocol not in (DEFAULT, found["name"]):
            raise VPRBenchError(f"The dataset given has one protocol, {found['id']} (its own positions and radius), "
                                f"not {shortened(repr(protocol))}: leave protocol out.")
        return
    # a name it does not have is refused as for the dataset by name, listing those it has
    if find_protocol(manifest, protocol).name != found["name"]:
        raise VPRBenchError(f"The dataset given was loaded under protocol {found['id']}, not {protocol!r}: load it "
                            f"under that one (load_dataset({dataset.name!r}, protocol={protocol!r})), or leave "
                            "protocol out.")


def benchmark_protocols(name: str) -> dict[str, dict]:
    """Hash -> protocol record of every protocol a benchmark's manifest defines, the default first;
    {} for a name that is no benchmark."""
    from ..datasets import dataset_manifests, protocols

    manifest = dataset_manifests().get(name)
    return {} if manifest is None else {p.hash: p.record() for p in protocols(manifest).values()}


def dataset_kind(dataset) -> str:
    """'benchmark' (read through a shipped manifest) or 'own' (a folder of the user's own, even
    one whose dataset.toml borrows a benchmark's name)."""
    return "own" if dataset.layout == "own" else getattr(dataset, "kind", None) or "benchmark"


def dataset_fingerprints(dataset, dataset_key: str, cache_dir=None) -> dict:
    found = {"dataset": dataset_key}
    if callable(getattr(dataset, "images_fingerprint", None)):
        found["images"] = dataset.images_fingerprint(cache_dir)
    if callable(getattr(dataset, "ground_truth_fingerprint", None)):
        found["ground_truth"] = dataset.ground_truth_fingerprint()
    return found


def fingerprint_of(name: str, fingerprints: dict) -> str:
    """`Dataset.fingerprint` from a record's parts (how older records are upgraded)."""
    return canonical_hash({"name": name, "images": fingerprints["images"], "ground_truth": fingerprints["ground_truth"]})
