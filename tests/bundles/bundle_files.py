"""Reading and writing bundle archives by hand, to tamper with them in tests (a module of its
own: test modules import it by name, and every test folder has a conftest)."""
from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path

import numpy as np

from vprbench.bundles.export import MANIFEST


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


def edit_record(members, edit, which=0) -> str:
    """Change a record of the bundle's members in place; returns its name."""
    name = record_names(members)[which]
    record = json.loads(members[name])
    edit(record)
    members[name] = json.dumps(record).encode()
    return name


def edit_arrays(members, edit, which=0) -> str:
    """Change a record's per-query arrays, and its sha256 to match (a careful forger)."""
    name = record_names(members)[which]
    record = json.loads(members[name])
    npz = name.rsplit("/", 1)[0] + "/" + record["per_query"]["file"]
    with np.load(io.BytesIO(members[npz])) as found:
        arrays = {k: found[k] for k in found.files}
    edit(arrays)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    members[npz] = buffer.getvalue()
    record["per_query"]["sha256"] = hashlib.sha256(members[npz]).hexdigest()
    members[name] = json.dumps(record).encode()
    return name


def respec(members, edit, which=0) -> str:
    """Change a record's spec (and what follows from it: keys, label, place, method card), as a
    careful forger would; returns the record's new name."""
    from vprbench.evaluation.results import card_of
    from vprbench.spec import RunSpec

    name = record_names(members)[which]
    folder, row_key = name.rsplit("/", 1)[0], name.split("/")[1]
    record = json.loads(members.pop(name))
    npz = members.pop(f"{folder}/{record['per_query']['file']}")
    card = json.loads(members.pop(f"methods/{row_key}.json"))
    edit(record)
    spec = RunSpec.model_validate(record["spec"])
    record.update(spec=spec.to_json(), spec_key=spec.key, row_key=spec.row_key, label=spec.label(), method=spec.method)
    folder = f"{record['protocol']['hash']}/{spec.row_key}"
    members[f"{folder}/{record['run_id']}.json"] = json.dumps(record).encode()
    members[f"{folder}/{record['per_query']['file']}"] = npz
    members[f"methods/{spec.row_key}.json"] = json.dumps({**card, **card_of(record)}).encode()
    return f"{folder}/{record['run_id']}.json"
