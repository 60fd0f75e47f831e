"""Reading and writing bundle archives by hand, to tamper with them in tests (a module of its
own: test modules import it by name, and every test folder has a conftest)."""
from __future__ import annotations

import hashlib
import io
import json
import tarfile
from pathlib import Path

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
