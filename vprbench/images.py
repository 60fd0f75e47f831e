"""Reading images, with errors that name the file at fault.

Only the formats of IMAGE_SUFFIXES are decoded, whatever a file's content claims: Pillow
would otherwise open, say, a PostScript file named .jpg and hand it to Ghostscript.
High-bit-depth images (16-bit PNG and TIFF, 32-bit integer or float TIFF) are scaled to
8 bits, not clipped.
"""
from __future__ import annotations

import re

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import VPRBenchError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".webp")
#: the Pillow decoders for IMAGE_SUFFIXES (JPEG includes multi-picture MPO files)
IMAGE_FORMATS = ("JPEG", "PNG", "BMP", "TIFF", "PPM", "WEBP")
#: full scale of Pillow's high-bit-depth modes: 16-bit integers ("I" is how Pillow widens
#: 16-bit files), float images in [0, 1]
_FULL_SCALE = {"I;16": 65535, "I;16B": 65535, "I;16L": 65535, "I;16N": 65535, "I": 65535, "F": 1.0}


def to_8bit(image: Image.Image) -> Image.Image:
    """An "L" image with a high-bit-depth image's values scaled from its full range to 0..255."""
    scale = _FULL_SCALE[image.mode]
    values = np.asarray(image, dtype=np.float64)
    return Image.fromarray(np.clip(np.rint(values * (255 / scale)), 0, 255).astype(np.uint8), "L")


def load_image(path: str | Path, mode: str = "RGB") -> Image.Image:
    """Open an image fully decoded in `mode` ("RGB" or "L")."""
    path = Path(path)
    try:
        with Image.open(path, formats=IMAGE_FORMATS) as image:
            image.load()
            return (to_8bit(image) if image.mode in _FULL_SCALE else image).convert(mode)
    except FileNotFoundError:
        raise VPRBenchError(f"Image not found: {path}") from None
    except PermissionError:
        raise  # not a corrupt image: the CLI names the path and what to do
    except Image.DecompressionBombError as error:
        raise VPRBenchError(f"Image {path} is too large to decode safely ({error}).") from None
    except UnidentifiedImageError:
        raise VPRBenchError(
            f"Cannot read image {path}: it is not a {', '.join(IMAGE_FORMATS)} image. Replace or remove the file."
        ) from None
    except (OSError, SyntaxError, ValueError) as error:
        raise VPRBenchError(
            f"Cannot read image {path}: {error}. Replace or remove the corrupt file."
        ) from None


def load_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 array."""
    return np.asarray(load_image(path, "RGB"))


def natural_key(path: Path) -> list:
    """Sort key treating digit runs as numbers (img2 < img10), as the authors' loaders do (natsort)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def list_images(folder: Path, *, recursive: bool = False, natural: bool = False) -> list[Path]:
    """The image files in `folder` (and below it when `recursive`), sorted by path, or in natural
    name order when `natural` (the order a released dataset's ground truth indexes)."""
    found = folder.rglob("*") if recursive else folder.iterdir()
    images = (p for p in found if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    return sorted(images, key=natural_key if natural else None)
