"""What a run's options name, by content: a file by its bytes, a folder by its files, a vocabulary
fitted on a benchmark by that benchmark's protocol (the spec's `files`)."""
from __future__ import annotations

from pathlib import Path

from .errors import VPRBenchError


def option_identities(method: str, options: dict, cache_dir=None) -> dict[str, str]:
    """Options whose value names an existing file are identified by its content, a folder
    (dense-vlad's vocabulary fitted on a folder of images) by its files' names and contents; a
    vocabulary fitted on a benchmark (dense-vlad's `vocabulary = "17places"`) by that benchmark's
    protocol hash."""
    from .datasets import dataset_manifest, dataset_manifests, find_protocol

    found = {}
    for name, value in options.items():
        if name == "vocabulary" and isinstance(value, str) and value in dataset_manifests():
            found[name] = f"protocol:{find_protocol(dataset_manifest(value), None).hash}"
            continue
        try:
            identity = file_identity(value) or folder_identity(value, cache_dir)
        except OSError as error:
            raise VPRBenchError(f"Method {method!r}: cannot read the file of option {name}, {value} "
                                f"({error.strerror or error}).") from None
        if identity is not None:
            found[name] = identity
    return found


def file_identity(value) -> str | None:
    """'sha256:<hex>' of the file `value` names (a file is identified by its bytes); None when it names none."""
    from .weights import file_sha256

    if isinstance(value, str) and value and Path(value).expanduser().is_file():
        return "sha256:" + file_sha256(Path(value).expanduser())
    return None


def folder_identity(value, cache_dir=None) -> str | None:
    """'folder:<hex>' over the names and bytes of the files under the folder `value` names (hidden
    ones aside), when written as a path ('./words', '/data/words', '~/w'): a bare word is a name
    ('map', a dataset), not the folder of that name the working directory may hold."""
    if not isinstance(value, str) or not value.startswith((".", "~", "/")) and "/" not in value:
        return None
    root = Path(value).expanduser()
    if not root.is_dir():
        return None
    from .datasets.identity import images_key

    files = sorted(p for p in root.rglob("*") if p.is_file()
                   and not any(part.startswith(".") for part in p.relative_to(root).parts))
    return "folder:" + images_key(files, root, cache_dir)
