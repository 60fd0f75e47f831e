"""SuperPoint + LightGlue re-ranking (Lindenberger, Sarlin & Pollefeys, ICCV 2023): per query and candidate,
SuperPoint keypoints of both images matched by LightGlue (kornia's implementation); a candidate's score is
its number of matches, or, with `model`, their RANSAC inliers (OpenCV USAC, as sift-ransac). Equal scores
keep the retrieval order.

Weights come from the one resolver (vprbench.weights): without `weights`, the authors' files are downloaded
once (no sha256 is published for either, so the download is not hash-checked); `weights=FOLDER` takes the
release files from a folder, each identified by its sha256; `weights=random` is a seeded random
initialisation, a pipeline check recorded as random, which fills no leaderboard cell. The files must be in
the official format: Magic Leap's state dict (conv1a ... convDb) and LightGlue's v0.1 one (self_attn.N,
cross_attn.N, ... renamed to kornia's transformers.N.* as kornia does); anything else is refused by name.

SuperPoint features are computed once per image into the feature store (keyed by the weights, the
extraction options and the library versions), so later runs (another retriever, another K) compute none.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator

from vprbench import VPRBenchError
from vprbench.images import DECODE_BUDGET_PIXELS
from vprbench.stages import Candidates, RerankOptions, Stage, StageContext
from vprbench.stages.geometric import C_INT_MAX
from vprbench.weight_source import WeightSource
from vprbench.weights import file_sha256, weights_identity, weights_provenance

NAME = "superpoint-lightglue"
RANDOM = "random"
RANDOM_SEED = 0
PASS_WITH = "--rerank-option weights=FOLDER (a folder holding both release files)"
#: Magic Leap's release, at the commit that holds it (a raw file of their repository)
SUPERPOINT = WeightSource(
    "superpoint_v1.pth",
    url="https://github.com/magicleap/SuperPointPretrainedNetwork/raw/1fda796addba9b6f8e79d586a3699700a86b1cea/"
        "superpoint_v1.pth",
    page="https://github.com/magicleap/SuperPointPretrainedNetwork", pass_with=PASS_WITH)
LIGHTGLUE = WeightSource(
    "superpoint_lightglue.pth",
    url="https://github.com/cvg/LightGlue/releases/download/v0.1_arxiv/superpoint_lightglue.pth",
    page="https://github.com/cvg/LightGlue", pass_with=PASS_WITH)
#: LightGlue for SuperPoint as released: 256-D descriptors, 9 layers, 4 heads
ARCHITECTURE = {"input_dim": 256, "descriptor_dim": 256, "n_layers": 9, "num_heads": 4}
#: LightGlue's buffer of early-stopping thresholds, computed from its configuration (not in the release)
DERIVED = "confidence_thresholds"


class SuperPointLightGlueOptions(RerankOptions):
    #: None: the authors' releases (downloaded once); a folder holding superpoint_v1.pth and
    #: superpoint_lightglue.pth; "random": seeded random weights (a pipeline check)
    weights: str | None = None
    #: SuperPoint keypoints kept per image, the strongest
    max_keypoints: int = Field(2048, ge=1)
    detection_threshold: float = Field(0.0005, gt=0, lt=1)
    nms_radius: int = Field(4, ge=0)
    #: the longer side SuperPoint sees (LightGlue's extractor: 1024); 0 = the image as stored; at
    #: most a square within the decode budget, the bound every image in vprbench has
    resize: int = Field(1024, ge=0, le=math.isqrt(DECODE_BUDGET_PIXELS))
    #: LightGlue's match confidence threshold, early stopping and point pruning (-1 turns either off)
    filter_threshold: float = Field(0.1, gt=0, lt=1)
    depth_confidence: float = Field(0.95, ge=-1, lt=1)
    width_confidence: float = Field(0.99, ge=-1, lt=1)
    #: "none": score = matches; else the inliers of a USAC fit of this model to them
    model: Literal["none", "fundamental", "homography"] = "none"
    threshold: float = Field(3.0, gt=0)
    confidence: float = Field(0.999, gt=0, lt=1)
    max_iterations: int = Field(10000, ge=1, le=C_INT_MAX)

    @field_validator("weights")
    @classmethod
    def _absolute(cls, value: str | None) -> str | None:
        """A folder is kept as an absolute path, so a plan run from elsewhere finds it."""
        return value if value in (None, RANDOM) else str(Path(value).expanduser().resolve())


# ---------------------------------------------------------------- weights
def release_files(folder: str) -> dict[str, Path]:
    """The two release files in `folder`, or one line saying what is missing and where to get it."""
    where = Path(folder)
    if not where.is_dir():
        raise VPRBenchError(f"Stage {NAME!r}: weights={folder} is not a folder; give a folder holding "
                            f"{SUPERPOINT.file_name} and {LIGHTGLUE.file_name} (or weights=random).")
    found = {}
    for source in (SUPERPOINT, LIGHTGLUE):
        path = where / source.file_name
        if not path.is_file():
            raise VPRBenchError(f"Stage {NAME!r}: {path} does not exist; download {source.file_name} from "
                                f"{source.where} into {where}.")
        found[source.file_name] = path
    return found


def _state(path: Path, what: str) -> dict:
    from vprbench.weights import read_weights_file

    try:
        state = read_weights_file(path, "weights file")
    except VPRBenchError as error:
        raise VPRBenchError(f"Stage {NAME!r}: {error} Give the release file {what} in its official format.") from None
    if not isinstance(state, dict) or not all(hasattr(v, "shape") for v in state.values()):
        raise VPRBenchError(f"Stage {NAME!r}: {path} does not hold a state dict of tensors (got "
                            f"{type(state).__name__}); give the release file {what} in its official format.")
    return state


def load_superpoint(path: Path | None):
    """SuperPoint with Magic Leap's weights from `path` (None: seeded random, already set up by the caller)."""
    from .common import load_exact
    from .superpoint import SuperPointNet

    net = SuperPointNet()
    if path is not None:
        load_exact(net, _state(path, SUPERPOINT.file_name), f"Stage {NAME!r}: {path} (SuperPoint, Magic Leap's layout)",
                   hint=f"Give Magic Leap's {SUPERPOINT.file_name} ({SUPERPOINT.page}).")
    return net.eval()


def lightglue_keys(state: dict, layers: int) -> dict:
    """The release's names (self_attn.N.*, cross_attn.N.*) as kornia's (transformers.N.self_attn.*), the
    renaming kornia's LightGlue applies to the released files."""
    renamed = {}
    for key, value in state.items():
        head, _, rest = key.partition(".")
        index, _, tail = rest.partition(".")
        if head in ("self_attn", "cross_attn") and index.isdigit() and int(index) < layers:
            key = f"transformers.{index}.{head}.{tail}"
        renamed[key] = value
    return renamed


def load_lightglue(path: Path | None, options: SuperPointLightGlueOptions):
    """kornia's LightGlue with the released architecture, its weights from `path` (None: seeded random)."""
    from kornia.feature import LightGlue

    from .common import load_exact

    matcher = LightGlue(features=None, **ARCHITECTURE, filter_threshold=options.filter_threshold,
                        depth_confidence=options.depth_confidence, width_confidence=options.width_confidence)
    if path is not None:
        state = lightglue_keys(_state(path, LIGHTGLUE.file_name), ARCHITECTURE["n_layers"])
        state.setdefault(DERIVED, getattr(matcher, DERIVED))
        load_exact(matcher, state, f"Stage {NAME!r}: {path} (LightGlue for SuperPoint, the v0.1 release layout)",
                   hint=f"Give LightGlue's {LIGHTGLUE.file_name} ({LIGHTGLUE.page}).")
    return matcher.eval()


def load_models(options: SuperPointLightGlueOptions, cache_dir=None, device: str = "cpu"):
    """(SuperPoint, LightGlue) on `device`, as `options.weights` says."""
    from vprbench.features.backbones import own_defaults
    from vprbench.weights import resolve_weights

    if options.weights == RANDOM:
        with own_defaults(RANDOM_SEED):  # float32 and these weights whatever the caller's torch defaults
            return load_superpoint(None).to(device), load_lightglue(None, options).to(device)
    paths = release_files(options.weights) if options.weights else {
        s.file_name: resolve_weights(s, None, f"Stage {NAME!r}", cache_dir=cache_dir).path for s in (SUPERPOINT, LIGHTGLUE)}
    with own_defaults():  # float32 under a caller's torch.set_default_dtype(torch.float64)
        return (load_superpoint(paths[SUPERPOINT.file_name]).to(device),
                load_lightglue(paths[LIGHTGLUE.file_name], options).to(device))


def weights_identities(options: SuperPointLightGlueOptions, cache_dir=None) -> dict[str, str | None]:
    """Release file -> the URL it is downloaded from or 'sha256:<hex>' of the local file (or of a file in
    `cache_dir` vprbench did not download); None for random."""
    if options.weights == RANDOM:
        return {SUPERPOINT.file_name: None, LIGHTGLUE.file_name: None}
    if options.weights:
        return {name: "sha256:" + file_sha256(path) for name, path in release_files(options.weights).items()}
    return {s.file_name: weights_identity(s, None, NAME, cache_dir) for s in (SUPERPOINT, LIGHTGLUE)}


# ---------------------------------------------------------------- the stage
#: weights (by content) this process has loaded once already: a plan's cells do not load them again
_CHECKED: set[tuple] = set()


class SuperPointLightGlue(Stage):
    track = "re-ranked"
    Options = SuperPointLightGlueOptions
    description = "SuperPoint keypoints matched by LightGlue (kornia); score = matches, or their RANSAC inliers"
    _cache_dir = None  # the run's cache, once applied

    @classmethod
    def file_identities(cls, options: SuperPointLightGlueOptions) -> dict:
        """A weights folder by the content of its two files; both are loaded now, so a file of another
        architecture is refused before any work."""
        if options.weights in (None, RANDOM):
            return {}
        identities = weights_identities(options)
        if tuple(sorted(identities.items())) not in _CHECKED:
            load_models(options)
            _CHECKED.add(tuple(sorted(identities.items())))
        return {"weights": identities}

    def feature_identity(self) -> dict:
        import kornia
        import torch

        from vprbench.images import ORIENTATION

        options = self.options
        weights = weights_identities(options, self._cache_dir)[SUPERPOINT.file_name]
        return {"extractor": "superpoint", "weights": weights or f"random:seed{RANDOM_SEED}",
                "max_keypoints": options.max_keypoints, "detection_threshold": options.detection_threshold,
                "nms_radius": options.nms_radius, "resize": options.resize, "torch": torch.__version__,
                "kornia": kornia.__version__, "decoding": ORIENTATION}

    def fingerprint(self) -> dict:
        import cv2
        import kornia
        import torch

        # the matches are kornia's LightGlue on torch, the inliers OpenCV's USAC: a sweep after an upgrade must run
        # again, as the SuperPoint features (keyed by these versions) are computed again
        return {"torch": torch.__version__, "kornia": kornia.__version__,
                **({"opencv": cv2.__version__} if self.options.model != "none" else {})}

    def _store(self, context: StageContext):
        return context.features("superpoint", self.feature_identity())

    def apply(self, candidates: Candidates, context: StageContext) -> Candidates:
        import torch

        from vprbench.images import load_rgb
        from vprbench.stages.base import rerank_by_counts
        from vprbench.stages.geometric import inliers

        from .superpoint import superpoint_features

        options, device = self.options, context.device
        self._cache_dir = context.cache_dir  # where the release files are read: their identity is theirs there
        superpoint, lightglue = load_models(options, context.cache_dir, device)  # refused before anything is stored

        def extract(path):
            return superpoint_features(superpoint, load_rgb(path), resize=options.resize, device=device,
                                       max_keypoints=options.max_keypoints, threshold=options.detection_threshold,
                                       nms_radius=options.nms_radius)

        def side(found):
            return {"keypoints": torch.from_numpy(found["points"])[None].to(device),
                    "descriptors": torch.from_numpy(found["descriptors"])[None].to(device),
                    "image_size": torch.from_numpy(found["size"])[None].to(device)}

        def count(query, other) -> int:
            pairs = lightglue({"image0": side(query), "image1": side(other)})["matches"][0].cpu().numpy()
            return len(pairs) if options.model == "none" else \
                inliers(query["points"][pairs[:, 0]], other["points"][pairs[:, 1]], options)

        with torch.inference_mode():
            return rerank_by_counts(self.name, candidates, context, self._store(context), extract, count)

    def stored_bytes(self, context: StageContext) -> int:
        return int(self._store(context).bytes_per_image("database") * context.database.row_count)

    def provenance(self) -> dict:
        """Each release file's source; the stage's is random, else user when either file is the user's."""
        files = {name: weights_provenance(identity)
                 for name, identity in weights_identities(self.options, self._cache_dir).items()}
        sources = {part["source"] for part in files.values()}
        source = next(s for s in ("random", "user", "official") if s in sources)
        return {"weights": {"source": source, "files": files}}
