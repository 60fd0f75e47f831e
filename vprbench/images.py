"""Reading images, with errors that name the file at fault."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from .errors import VPRBenchError

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".webp")


def load_image(path: str | Path, mode: str = "RGB") -> Image.Image:
    """Open an image fully decoded in `mode` ("RGB" or "L")."""
    path = Path(path)
    try:
        with Image.open(path) as image:
            image.load()
            return image.convert(mode)
    except FileNotFoundError:
        raise VPRBenchError(f"Image not found: {path}") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as error:
        raise VPRBenchError(
            f"Cannot read image {path}: {error}. Replace or remove the corrupt file."
        ) from None


def load_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 array."""
    return np.asarray(load_image(path, "RGB"))


def list_images(folder: Path) -> list[Path]:
    """Image files directly in `folder`, sorted by name (the order ground truth indexes)."""
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
