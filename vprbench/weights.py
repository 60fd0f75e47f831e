"""Weight files, for every method that loads them: where they come from (the one resolver:
a local file, the authors' release URL checked against a published sha256, or a Hugging Face
hub file), read safely, named by their content."""
from __future__ import annotations

import contextlib
import glob
import json
import os
import pickle
import re
import struct
import tomllib
import warnings
from dataclasses import dataclass
from functools import cache
from importlib.resources import files
from pathlib import Path

from . import fsutil
from .errors import VPRBenchError, network_reason, require
from .paths import cache_root, regular_file
from .weight_source import WeightSource

_SHA256: dict[tuple, str] = {}


def _sha256_key(path: Path) -> tuple:
    stat = path.stat()
    return str(path.resolve()), stat.st_mtime_ns, stat.st_size


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes; remembered per (path, mtime, size), so multi-GB files hash once."""
    key = _sha256_key(Path(path))
    if key not in _SHA256:
        _SHA256[key] = fsutil.file_sha256(path)
    return _SHA256[key]


def _numpy_globals() -> list:
    """numpy scalars/arrays that training checkpoints pickle beside the tensors (scores, recalls),
    under their numpy 1.x and 2.x module names."""
    import numpy as np

    try:
        from numpy._core import multiarray
    except ImportError:  # numpy 1.x
        from numpy.core import multiarray
    allowed = [np.dtype, np.ndarray]
    allowed += [getattr(np.dtypes, n) for n in dir(np.dtypes) if n.endswith("DType")]
    for module in ("numpy.core.multiarray", "numpy._core.multiarray"):
        allowed += [(multiarray.scalar, f"{module}.scalar"), (multiarray._reconstruct, f"{module}._reconstruct")]
    return allowed


#: a damaged file's remedy; one in the cache would otherwise be served again by its name
GET_AGAIN = ("a download or copy that stopped early leaves such a file: get it again (one vprbench downloaded: "
             "delete it, and the next run downloads it anew).")


def read_torch_file(path: str | Path, what: str = "checkpoint", *, mmap: bool = False, remedy: str = GET_AGAIN):
    """torch.load of tensors, containers and numpy scalars only: loading never runs code.

    `mmap` maps large zip-format files instead of copying them (legacy files are read whole).
    Any failure is a VPRBenchError naming the file; a damaged one also says `remedy`.
    """
    import torch

    from .methods.checks import flag

    mmap = flag("read_torch_file", "mmap", mmap)  # 'no' would be truthy
    regular_file(path, what.capitalize())  # before torch: a named pipe would hang it, None fail deep inside
    path = Path(path)
    # torch.load reads any path named *.safetensors as safetensors; this reads PyTorch files, whatever
    # their name: such a file is given as an open file (which cannot be mapped)
    named_safetensors = path.name.endswith(".safetensors")
    try:
        # torch's notice on a pickle protocol it was not written with is for its developers, not a user
        with torch.serialization.safe_globals(_numpy_globals()), warnings.catch_warnings(), \
                (open(path, "rb") if named_safetensors else contextlib.nullcontext(path)) as source:
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            try:
                return torch.load(source, map_location="cpu", weights_only=True, mmap=mmap and not named_safetensors)
            except RuntimeError:
                if not mmap or named_safetensors:
                    raise
                return torch.load(path, map_location="cpu", weights_only=True)  # legacy format cannot be mapped
    except pickle.UnpicklingError as error:
        try:
            extra = ", ".join(torch.serialization.get_unsafe_globals_in_checkpoint(path))
        except (RuntimeError, ValueError, OSError):  # only zip-format files can be inspected: else the refusal names it
            extra = ", ".join(dict.fromkeys(re.findall(r"GLOBAL ([\w.]+)", str(error))))
        if not extra:
            raise VPRBenchError(f"Cannot read {what} {path}: it is damaged or not a PyTorch file; {remedy}") from None
        raise VPRBenchError(
            f"{what.capitalize()} {path} also holds Python objects ({extra}), which are not loaded because "
            "unpickling them can run code. If you trust the file, save its weights alone, e.g. "
            "torch.save(torch.load(FILE, weights_only=False)['state_dict'], 'weights.pth'), and pass that."
        ) from None
    except (RuntimeError, EOFError, OSError, KeyError, ValueError, IndexError, struct.error) as error:
        # what torch's unpickler raises on truncated or foreign files; its first sentence (torch goes on
        # about its zip reader's internals and how checkpoints get corrupted)
        if isinstance(error, OSError) and error.errno is not None:  # not readable (permissions, a folder): not damaged
            raise VPRBenchError(f"Cannot read {what} {path}: {os.strerror(error.errno)}; check that it is a file "
                                "this user may read.") from None
        reason = str(error).strip().splitlines()[0].split(". ")[0].rstrip(".") if str(error).strip() else ""
        raise VPRBenchError(
            f"Cannot read {what} {path}: it is damaged or not a PyTorch file ({type(error).__name__}"
            f"{': ' + reason if reason else ''}); {remedy}") from None


# ---------------------------------------------------------------- the one resolver
@dataclass(frozen=True)
class ResolvedWeights:
    """A weight file on disk and its identity for fingerprints: 'sha256:<hex>' of a local file or of a
    release whose sha256 a backbone manifest pins, else the release URL or 'hf:<repo>/<file>'."""

    path: Path
    identity: str


def weights_folder(cache_dir=None) -> Path:
    """Where downloaded weight files are kept: torch hub's layout under the cache folder."""
    return cache_root(cache_dir) / "torch" / "hub" / "checkpoints"


def hub_folder(cache_dir=None) -> Path:
    """The Hugging Face hub cache used for hub downloads, under the cache folder."""
    return cache_root(cache_dir) / "huggingface"


def local_weights(source: WeightSource, weights: str | Path, what: str) -> Path:
    """The file `weights` names (a folder of release files gives `source`'s file), checked to exist."""
    if not str(weights).strip():  # Path('') is the working folder: its copy of the release would be loaded
        raise VPRBenchError(f"{what}: --weights {weights!r} names no file: give a weights file (or a folder holding "
                            f"{source.file_name}), or leave --weights out.")
    path = Path(weights).expanduser()
    if path.is_dir():
        names = (source.file_name, *source.also_named)
        path = next((path / name for name in names if (path / name).is_file()), path / source.file_name)
    if not path.is_file() and str(weights) == "random":  # AnyLoc's backbones and some stages take it before here
        raise VPRBenchError(f"{what}: weights 'random' (random initialisation) are only for AnyLoc backbones and "
                            "the stages that take them; pass a weights file in the official format instead: "
                            f"{source.how_to_get()}.")
    if not regular_file(path, f"{what}: weights file"):
        gated = f" The weights are gated ({source.licence}): request access at {source.page or source.where} first." \
            if source.gated else ""
        raise VPRBenchError(f"{what}: weights file {path} does not exist; {source.how_to_get()}.{gated}")
    return path


def cached_weights(source: WeightSource, cache_dir=None) -> Path | None:
    """The release's file if one is already in the cache (nothing is downloaded): it is there, not
    proven the release's (`cached_identity` says which it is)."""
    if source.url:
        path = weights_folder(cache_dir) / source.file_name
        return path if path.is_file() else None
    if source.hub:
        from huggingface_hub import try_to_load_from_cache

        for name in (source.file_name, *source.also_named):
            found = try_to_load_from_cache(source.hub, name, cache_dir=str(hub_folder(cache_dir)))
            if isinstance(found, str):
                return Path(found)
    return None


def release_identity(source: WeightSource, what: str) -> str:
    """The identity of the authors' release: a pinned sha256 (as a local copy of its bytes is: one
    computation, one identity; only there, as its records still name its URL from the pin, see
    `weights_provenance`), else its URL or 'hf:<repo>/<file>'."""
    if source.url:
        pinned = f"sha256:{source.sha256.lower()}" if source.sha256 else None
        return pinned if pinned and weights_provenance(pinned).get("url") == source.url else source.url
    if source.hub:
        return f"hf:{source.hub}/{source.file_name}"
    raise VPRBenchError(_no_download(source, what))


def _download_record(digest: str, cache_dir=None) -> Path:
    """Where vprbench records a download it made, keyed by the downloaded bytes' sha256 (not by the
    file's name: any bytes may be put under a release's name)."""
    return cache_root(cache_dir) / "weights-downloads" / f"{digest}.json"


def record_download(source: WeightSource, path: Path, what: str, cache_dir=None) -> str:
    """After vprbench downloaded `path` from `source`: the record that these bytes are the release's
    (written atomically before the file takes its place). Returns the file's sha256."""
    digest = file_sha256(path)
    fsutil.atomic_write(_download_record(digest, cache_dir), json.dumps(
        {"identity": release_identity(source, what), "from": source.where, "file": source.file_name, "sha256": digest}))
    return digest


def cached_identity(source: WeightSource, path: Path, what: str, cache_dir=None) -> str:
    """The identity of a file found in the cache: the release's when vprbench recorded downloading
    these very bytes from it, else its sha256, as the same file given with --weights (official only
    when the authors publish that sha256): a file put there by hand proves nothing by its name."""
    digest = file_sha256(path)
    try:
        said = json.loads(_download_record(digest, cache_dir).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        said = None
    official = release_identity(source, what)
    proven = isinstance(said, dict) and said.get("sha256") == digest and said.get("identity") == official
    return official if proven else f"sha256:{digest}"


def weights_identity(source: WeightSource, weights: str | Path | None, what: str, cache_dir=None) -> str:
    """The identity `resolve_weights` gives, without downloading anything: a local file's sha256, a
    file already in `cache_dir` as `cached_identity` says, else the release's (`release_identity`)."""
    if weights is not None:
        return "sha256:" + file_sha256(local_weights(source, weights, what))
    found = cached_weights(source, cache_dir)
    return release_identity(source, what) if found is None else cached_identity(source, found, what, cache_dir)


def _not_downloaded(source: WeightSource, path: Path, identity: str, what: str) -> str:
    return (f"{what}: {path} is not a file vprbench downloaded from {source.where} (no record of a download of "
            f"these bytes), and no published sha256 names it: it runs as your own weights, as with --weights, "
            f"and its results are marked 'user weights {identity[:19]}'; delete it and vprbench downloads the "
            "release, recorded as official.")


def _gated(source: WeightSource, what: str) -> VPRBenchError:
    licence = f" ({source.licence})" if source.licence else ""
    own = f" (the authors' release: {source.page})" if source.page and source.page != source.where else ""
    return VPRBenchError(f"{what}: the weights are gated{licence}: request access at {source.where} and log in "
                         f"('hf auth login'), or pass the file you have{own} with {source.pass_with}; "
                         "--weights random runs a pipeline check without them.")


def _hash_mismatch(source: WeightSource, got: str, what: str) -> VPRBenchError:
    """A download whose bytes are not the release's: both sha256 in full (none is kept), not "Offline?"."""
    return VPRBenchError(f"{what}: the download of {source.file_name} from {source.url} has sha256 {got.lower()}, "
                         f"not the published {source.sha256.lower()}, and was not kept: the file changed at the source "
                         f"or was damaged on the way; try again, or {source.how_to_get()} once its sha256 is the "
                         "published one.")


def _no_download(source: WeightSource, what: str) -> str:
    return (f"{what}: the authors publish {source.file_name} only at {source.where}, which cannot be downloaded "
            f"automatically; download it there and pass it with {source.pass_with}.")


def resolve_weights(source: WeightSource, weights: str | Path | None, what: str, *, cache_dir=None) -> ResolvedWeights:
    """The file a method loads: the user's `weights` (a file, or a folder holding the release's
    file name), else the release downloaded once into `cache_dir` (checked against the published
    sha256 when there is one). Offline, or without a download, the error says how to supply it."""
    if weights is not None:
        path = local_weights(source, weights, what)
        return ResolvedWeights(path, weights_identity(source, path, what))
    identity = release_identity(source, what)  # the source is one that downloads: else said here
    found = cached_weights(source, cache_dir)
    if found is not None:
        identity = cached_identity(source, found, what, cache_dir)
        if identity.startswith("sha256:") and weights_provenance(identity)["source"] == "user":
            fsutil.warn_once(found, _not_downloaded(source, found, identity, what))
        return ResolvedWeights(found, identity)
    try:
        if source.url:
            import torch

            found = weights_folder(cache_dir) / source.file_name
            found.parent.mkdir(parents=True, exist_ok=True)
            # one download at a time per file: a second run waits, then finds it; the '.partial' files
            # torch leaves when killed are then dead ones' (torch never removes them)
            with fsutil.lock(found.with_name(f".{found.name}.lock"), what=f"the download of {found}"):
                for partial in found.parent.glob(f"{glob.escape(found.name)}.*.partial"):
                    partial.unlink(missing_ok=True)
                if not found.is_file():
                    # into a name of its own, recorded, then in place: the file is never there unrecorded
                    staging = found.with_name(f"{found.name}.download")
                    try:
                        torch.hub.download_url_to_file(source.url, str(staging), progress=False,
                                                       hash_prefix=source.sha256 and source.sha256.lower())  # lower-case hex
                    except RuntimeError as error:  # torch keeps nothing of a file whose hash differs
                        got = re.search(r'invalid hash value .*got "([0-9a-fA-F]+)"', str(error))
                        if got is None:
                            raise
                        raise _hash_mismatch(source, got.group(1), what) from None
                    digest = record_download(source, staging, what, cache_dir)
                    os.replace(staging, found)
                    _SHA256[_sha256_key(found)] = digest  # a multi-GB file is not read again for its identity
        else:
            from huggingface_hub import get_hf_file_metadata, hf_hub_download, hf_hub_url
            from huggingface_hub.errors import EntryNotFoundError, LocalEntryNotFoundError

            # one request without the hub client's retries first: an offline machine or a gated
            # repository is told at once, not after half a minute of retrying; a file the repository
            # lacks: the next name (its weights under timm's other name)
            names = (source.file_name, *source.also_named)
            for name in names:
                try:
                    get_hf_file_metadata(hf_hub_url(source.hub, name), retry_on_errors=False)
                    break
                except EntryNotFoundError as error:
                    if isinstance(error, LocalEntryNotFoundError) or name == names[-1]:  # offline, or none there
                        raise
            found = Path(hf_hub_download(source.hub, name, cache_dir=str(hub_folder(cache_dir))))
            record_download(source, found, what, cache_dir)
    except VPRBenchError:
        raise
    except Exception as error:  # noqa: BLE001 - network clients raise their own types (urllib, httpx, hub errors)
        if type(error).__name__ == "GatedRepoError":  # not logged in, or logged in without access
            raise _gated(source, what) from None
        gated = f" The model is gated ({source.licence}): access is requested at {source.page or source.where}." \
            if source.gated else ""
        raise VPRBenchError(f"{what}: could not download {source.file_name} from {source.where} "
                            f"({network_reason(error)}). Offline? {source.how_to_get()}.{gated}") from None
    return ResolvedWeights(found, identity)


def read_weights_file(path: str | Path, what: str = "weights file"):
    """A checkpoint's content: a .safetensors file's tensors, else `read_torch_file`."""
    regular_file(path, what.capitalize())
    path = Path(path)
    if _safetensors_content(path):
        from safetensors import SafetensorError
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except (SafetensorError, OSError, ValueError, RuntimeError) as error:
            raise VPRBenchError(f"Cannot read {what} {path}: {error}. Is it the complete .safetensors file?") from None
    return read_torch_file(path, what, mmap=True)


def _safetensors_content(path: Path) -> bool:
    """Read as .safetensors by content, not name (a hub file saved as .pth, a PyTorch file named
    .safetensors): an 8-byte header length then '{'; PyTorch files start as a zip ('PK') or a pickle."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(9)
    except OSError as error:
        raise VPRBenchError(f"Cannot read weights file {path}: {error.strerror or error}.") from None
    if len(head) == 9 and head[8:] == b"{" and 0 < int.from_bytes(head[:8], "little") < path.stat().st_size:
        return True
    return path.suffix == ".safetensors" and not (head.startswith(b"PK") or head.startswith(b"\x80"))


@cache
def official_releases() -> tuple[dict, ...]:
    """The official weight releases vprbench knows (manifests/weights.toml)."""
    text = (files("vprbench.manifests") / "weights.toml").read_text(encoding="utf-8")
    return tuple(tomllib.loads(text)["release"])


def is_file_identity(identity) -> bool:
    """Whether `identity` names a weights file by its content: 'sha256:' and 64 hex digits."""
    return isinstance(identity, str) and re.fullmatch(r"sha256:[0-9a-fA-F]{64}", identity) is not None


def weights_provenance(identity: str | None) -> dict:
    """Where a method's weights came from, for result records and the leaderboard.

    `identity` is what fingerprints hold: the official URL (or 'hf:<repo>/<file>') of a file
    vprbench downloaded from the authors' release (or another source's 'SOURCE:NAME', e.g. an
    open_clip model), 'sha256:<hex>' for a local file (or one in the cache vprbench did not download)
    or a release with a published sha256, None for a model run without weights (random
    initialisation); other text is refused. A
    sha256 is official only when it equals one the authors publish (a backbone manifest's pinned
    sha256, or manifests/weights.toml); otherwise it is the user's file.
    """
    if identity is None:
        return {"source": "random"}
    require(identity, str, "weights_provenance takes a weights identity (a URL, 'hf:REPO/FILE' or 'sha256:HEX'), "
                           "or None for random weights")
    if not re.fullmatch(r"[A-Za-z][\w+.-]*:\S+", identity) or identity.startswith("sha256:") and not \
            is_file_identity(identity):  # else any text (a bare file name) is recorded as official weights
        raise VPRBenchError(f"weights_provenance takes a weights identity (a URL, 'hf:REPO/FILE', a source's "
                            f"'SOURCE:NAME' or 'sha256:' and 64 hex digits), or None for random weights; got {identity!r}.")
    if identity.startswith("hf:"):
        repo, _, name = identity.removeprefix("hf:").rpartition("/")
        return {"source": "official", "hub": repo, "file": name, "recognised_by": "download"}
    if not identity.startswith("sha256:"):
        release = next((r for r in official_releases() if identity.startswith(r["url_prefix"])), None)
        return {"source": "official", "url": identity, "recognised_by": "download",
                **({"release": release["name"]} if release else {})}
    digest = identity.removeprefix("sha256:")
    from .features.catalogue import backbones  # pydantic: not loaded where only a file is hashed

    url = next((e.url for e in backbones().values() if e.url and e.sha256 and e.sha256.lower() == digest.lower()), None)
    if url is not None:  # a pinned release's bytes, downloaded or a local copy alike: its URL and sha256
        release = next((r for r in official_releases() if url.startswith(r["url_prefix"])), None)
        return {"source": "official", "url": url, "sha256": digest, "recognised_by": "sha256",
                **({"release": release["name"]} if release else {})}
    for release in official_releases():
        for name, published in release.get("sha256", {}).items():
            if published.lower() == digest.lower():
                return {"source": "official", "sha256": digest, "recognised_by": "sha256",
                        "release": release["name"], "file": name, "checksum_source": release.get("checksum_source", "")}
    return {"source": "user", "sha256": digest}
