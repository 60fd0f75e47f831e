"""Where the authors publish a checkpoint: what the weights resolver (vprbench.weights) downloads
or asks for, as backbone manifests and methods state it."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class WeightSource:
    """Where the authors publish a checkpoint.

    `url` is a direct download of the release; `hub` a Hugging Face hub repository holding
    `file_name` (used when there is no `url`); `page` is where a person gets the file when
    neither can be downloaded (Google Drive, a gated model); `sha256` only when the authors
    publish one (a download that does not match it is refused). `gated`: access must be
    requested first (under `licence`), so nothing is downloaded without being logged in.
    """

    file_name: str
    url: str | None = None
    hub: str | None = None
    page: str | None = None
    sha256: str | None = None
    #: how a local copy is given, in messages (a stage takes it as an option)
    pass_with: str = "--weights PATH"
    gated: bool = False
    licence: str | None = None
    #: other names a folder of release files may hold it under (the authors' own download scripts'), and
    #: other files of a hub repository holding it, tried in this order after `file_name` (timm's)
    also_named: tuple[str, ...] = ()

    @property
    def where(self) -> str:
        if self.url:
            return self.url
        if self.hub:
            return f"https://huggingface.co/{self.hub}"
        return self.page or "the authors' release page"

    def how_to_get(self) -> str:
        return f"download {self.file_name} from {self.where} and pass it with {self.pass_with}"
