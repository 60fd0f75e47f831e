"""What a run's options name, by content: a file by its bytes, a folder by its files, a vocabulary
fitted on a benchmark by that benchmark's protocol (the spec's `files`)."""
from __future__ import annotations

import errno
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
            identity = value_identity(name, value, cache_dir)
        except OSError as error:
            if error.errno == errno.ENAMETOOLONG:  # no file is named so: a value the method's own check judges
                continue
            raise VPRBenchError(f"Method {method!r}: cannot read the file of option {name}, {value} "
                                f"({error.strerror or error}).") from None
        if identity is not None:
            found[name] = identity
    return found


def value_identity(option: str, value, cache_dir=None) -> str | None:
    """What a method's or a stage's option names, by content: a file, or a folder. A bare word is taken
    for a name, but `weights` take no names ('random' aside, which no folder is): a bare word naming a
    folder is that folder (weights.local_weights loads the release's file from it), as for a file the
    word is kept."""
    if option == "weights" and value == "random":  # random initialisation whatever the working directory holds
        return None
    return file_identity(value) or folder_identity(value, cache_dir, bare_word=option == "weights")


def file_identity(value) -> str | None:
    """'sha256:<hex>' of the file `value` names (a file is identified by its bytes); None when it names
    none. A bare word ('key', 'map', 'urban') may be a name the method knows, not the file of that name
    the working directory holds: its identity keeps the word ('key@sha256:<hex>'), or two files of one
    content made facet=key and facet=value one run."""
    from .weights import file_sha256

    if not isinstance(value, str) or not value or not Path(value).expanduser().is_file():
        return None
    digest = "sha256:" + file_sha256(Path(value).expanduser())
    return digest if _written_as_path(value) or Path(value).suffix else f"{value}@{digest}"


def folder_identity(value, cache_dir=None, *, bare_word: bool = False) -> str | None:
    """'folder:<hex>' over the names and bytes of the files under the folder `value` names (hidden
    ones aside), when written as a path ('./words', '/data/words', '~/w'): a bare word is a name
    ('map', a dataset), not the folder of that name the working directory may hold; with `bare_word`
    it is that folder too ('ckpt@folder:<hex>')."""
    if not isinstance(value, str) or not value or not (_written_as_path(value) or bare_word):
        return None
    root = Path(value).expanduser()
    if not root.is_dir():
        return None
    from .datasets.identity import images_key

    files = sorted(p for p in root.rglob("*") if p.is_file()
                   and not any(part.startswith(".") for part in p.relative_to(root).parts))
    digest = "folder:" + images_key(files, root, cache_dir)
    return digest if _written_as_path(value) else f"{value}@{digest}"


def _written_as_path(value: str) -> bool:
    return value.startswith((".", "~", "/")) or "/" in value
