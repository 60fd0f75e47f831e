"""Reading images, with errors that name the file at fault.

Only the formats of IMAGE_SUFFIXES are decoded, whatever a file's content claims: Pillow
would otherwise open, say, a PostScript file named .jpg and hand it to Ghostscript.
High-bit-depth images (16-bit PNG and TIFF, 32-bit integer or float TIFF) are scaled to
8 bits, not clipped. An image's size is read from its header and checked against the decode
budget (DECODE_BUDGET_PIXELS) before any pixel is decoded: a small file can declare a huge
image. EXIF orientation is applied (ORIENTATION): a photo stored sideways with an orientation
tag, as phones write them, is seen upright, as a person viewing it sees it.

An image is read into memory once and decoded from those bytes; inside `reads_seen()` the
sha256 of exactly the bytes decoded is recorded, so the loader can prove a row describes the
image its store is keyed by (not a copy that changed before or while it was read).
"""
from __future__ import annotations

import hashlib
import io
import os
import re
import struct
import threading
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from .errors import ShardWarning, VPRBenchError
from .fsutil import warn_once
from .paths import regular_file

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".ppm", ".webp")
#: the Pillow decoders for IMAGE_SUFFIXES (JPEG includes multi-picture MPO files)
IMAGE_FORMATS = ("JPEG", "PNG", "BMP", "TIFF", "PPM", "WEBP")
#: full scale of Pillow's high-bit-depth modes: 16-bit integers ("I" is how Pillow widens
#: 16-bit files), float images in [0, 1]
_FULL_SCALE = {"I;16": 65535, "I;16B": 65535, "I;16L": 65535, "I;16N": 65535, "I": 65535, "F": 1.0}

#: The most pixels (width x height) an image may have to be decoded: 89,478,485, Pillow's own
#: decompression-bomb limit (2**30 / 12). It admits every camera image of the benchmarks (a
#: Tokyo 24/7 query, among the largest, is 3264 x 2448 = 8 M pixels) and phone photos up to 64 MP
#: (9248 x 6936); a larger image is refused, naming its size, before it is decoded. Decoding
#: takes about DECODE_BYTES_PER_PIXEL bytes a pixel at peak (the growth of load_rgb's peak resident
#: memory on 6000 x 6000 images, 8-bit JPEG and 16-bit PNG alike): 0.83 GiB at the budget.
DECODE_BUDGET_PIXELS = 89_478_485
DECODE_BYTES_PER_PIXEL = 10
#: The largest image file read: 8 bytes a pixel of the budget (uncompressed 16-bit RGBA); any
#: real image within the decode budget is smaller.
MAX_FILE_BYTES = DECODE_BUDGET_PIXELS * 8
#: How images are oriented for every method; the result record says so.
ORIENTATION = "exif-applied"

_watch = threading.local()


@contextmanager
def reads_seen():
    """While open, `load_image` records {absolute path: sha256 of the bytes it decoded}."""
    seen: dict[str, str] = {}
    previous, _watch.seen = getattr(_watch, "seen", None), seen
    try:
        yield seen
    finally:
        _watch.seen = previous


def _read_bytes(path: Path) -> bytes:
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > MAX_FILE_BYTES:
            raise VPRBenchError(f"Image {path} is a {size / 2**30:.1f} GiB file, larger than any image within the "
                                f"decode budget ({MAX_FILE_BYTES / 2**30:.1f} GiB, vprbench.images.MAX_FILE_BYTES). "
                                "Downscale or recompress it, or remove it.")
        data = f.read()
    seen = getattr(_watch, "seen", None)
    if seen is not None:
        seen[os.path.abspath(path)] = hashlib.sha256(data).hexdigest()
    return data

def check_decode_budget(width: int, height: int, what: str,
                        advice: str = "Downscale it (e.g. to 8000 pixels on its longer side) or remove it.") -> None:
    """Refuse (VPRBenchError, naming `what` and saying `advice`) width x height pixels above the budget."""
    pixels = int(width) * int(height)
    if pixels > DECODE_BUDGET_PIXELS:
        raise VPRBenchError(
            f"{what} is {width} x {height} = {pixels:,} pixels, above the decode budget of "
            f"{DECODE_BUDGET_PIXELS:,} pixels (vprbench.images.DECODE_BUDGET_PIXELS; decoding it would need about "
            f"{pixels * DECODE_BYTES_PER_PIXEL / 2**30:.1f} GiB). {advice}"
        )


def to_8bit(image: Image.Image) -> Image.Image:
    """An "L" image with a high-bit-depth image's values scaled from its full range to 0..255
    (rounded to the nearest; in integers for 16-bit images, 4 bytes a pixel at most)."""
    values = np.asarray(image)
    if image.mode == "F":
        scaled = np.clip(np.rint(values.astype(np.float32) * np.float32(255)), 0, 255)
    else:  # round(v * 255 / 65535) = (2v + 257) // 514 exactly, as v / 257 is never a half
        scaled = np.clip(values, 0, 65535).astype(np.int32)
        scaled *= 2
        scaled += 257
        scaled //= 514
    return Image.fromarray(scaled.astype(np.uint8), "L")


def _beyond_full_scale(image: Image.Image) -> float:
    """The largest finite value of a float image above its full scale 1 (most often one written in 0..255), else 0."""
    if image.mode != "F":
        return 0.0
    values = np.asarray(image)
    top = float(np.max(values, initial=0.0, where=np.isfinite(values)))
    return top if top > _FULL_SCALE["F"] else 0.0


def load_image(path: str | Path, mode: str = "RGB") -> Image.Image:
    """Open an image fully decoded in `mode` ("RGB" or "L"), upright (EXIF orientation applied)."""
    path = Path(path)
    try:
        # Pillow's warnings name no file (a damaged EXIF block): recorded here, said below naming it
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            image = Image.open(io.BytesIO(_read_bytes(path)), formats=IMAGE_FORMATS)
            with image:
                check_decode_budget(*image.size, f"Image {path}")  # from the header: nothing decoded yet
                image.load()
                ImageOps.exif_transpose(image, in_place=True)
                brightest = _beyond_full_scale(image)
                loaded = (to_8bit(image) if image.mode in _FULL_SCALE else image).convert(mode)
        _say_again(said, path)
        if brightest:  # said here, not among Pillow's warnings; once per image however often it is read
            warn_once(path, f"Image {path}: a float image with values up to {brightest:g} is read as values in "
                            "[0, 1] (1 is white, above it clipped), so it reads almost white: save it as 8- or "
                            "16-bit integers, or as floats scaled to [0, 1].", stacklevel=2, category=ShardWarning)
        return loaded
    except FileNotFoundError:
        raise VPRBenchError(f"Image not found: {path}") from None
    except PermissionError:
        raise  # not a corrupt image: the CLI names the path and what to do
    except Image.DecompressionBombError as error:  # Pillow's own check, at twice the budget, as it opens
        found = re.search(r"\((\d+) pixels\)", str(error))
        size = f"{int(found.group(1)):,} pixels" if found else "more than twice that many pixels"
        raise VPRBenchError(
            f"Image {path} has {size}, above the decode budget of {DECODE_BUDGET_PIXELS:,} pixels "
            "(vprbench.images.DECODE_BUDGET_PIXELS). Downscale it (e.g. to 8000 pixels on its longer side) or remove it."
        ) from None
    except UnidentifiedImageError:
        raise VPRBenchError(
            f"Cannot read image {path}: it is not a {', '.join(IMAGE_FORMATS)} image. Replace or remove the file."
        ) from None
    except (OSError, SyntaxError, ValueError, TypeError, KeyError, IndexError, EOFError, struct.error) as error:
        # damaged pixels or a damaged EXIF block (whose orientation cannot then be trusted)
        raise VPRBenchError(
            f"Cannot read image {path}: {str(error) or type(error).__name__}. Replace or remove the corrupt file."
        ) from None


#: Pillow warnings not passed on: what check_decode_budget refuses itself, naming the file; and a
#: palette's transparency, which RGB drops, as the authors' loaders' convert("RGB") does
_UNSAID = re.compile(r"Palette images with Transparency")


def _say_again(said: list, path: Path) -> None:
    """Each warning Pillow gave while reading `path`, once, naming the file."""
    texts = [str(w.message).strip() for w in said if not issubclass(w.category, Image.DecompressionBombWarning)]
    for text in dict.fromkeys(t for t in texts if not _UNSAID.match(t)):
        warnings.warn(f"Image {path}: Pillow warns {text!r}; it is read as Pillow reads it (replace the file if "
                      "it is damaged).", ShardWarning, stacklevel=3)


def load_rgb(path: str | Path) -> np.ndarray:
    """HxWx3 uint8 array."""
    return np.asarray(load_image(path, "RGB"))


def natural_key(path: Path) -> list:
    """Sort key treating digit runs as numbers (img2 < img10), as the authors' loaders do (natsort)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.name)]


def list_images(folder: Path, *, recursive: bool = False, natural: bool = False) -> list[Path]:
    """The image files in `folder` (and below it when `recursive`), sorted by path, or in natural
    name order when `natural` (the order a released dataset's ground truth indexes); names alike in
    natural order ('a1.jpg', 'a01.jpg'; one name in two subfolders) by path, not as the folder lists them."""
    found = entries_below(folder) if recursive else folder.iterdir()
    # hidden names (macOS's ._x.jpg copies of metadata) are no images, as for the authors' glob-based loaders
    images = [utf8_name(p) for p in found
              if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".") and _is_image_file(p)]
    return sorted(images, key=(lambda p: (natural_key(p), p)) if natural else None)


def entries_below(folder: Path) -> Iterator[Path]:
    """Every entry below `folder`, linked folders followed as the top folder's are (rglob skipped them, dropping
    their images unseen), except hidden folders and a link back up to a folder it lies in (a loop; `..` would add the
    other split); each real folder once, so other loops end too; an unreadable folder is an error."""
    seen = set()

    def refuse(error: OSError):
        raise error

    for top, folders, files in os.walk(folder, onerror=refuse, followlinks=True):
        found, here = os.stat(top), Path(top).resolve()
        if (found.st_dev, found.st_ino) in seen:
            folders.clear()
            continue
        seen.add((found.st_dev, found.st_ino))
        folders[:] = [name for name in folders
                      if not name.startswith(".") and not here.is_relative_to((Path(top) / name).resolve())]
        yield from (Path(top) / name for name in folders + files)


def nested_image_folders(folder: Path) -> str:
    """The subfolders of `folder` that hold images (at any depth), named for a message; "" if none: the images
    `list_images` leaves out, which an own folder and `describe --fit-on` say."""
    # the folder's own images were listed already: only its folders, walked as list_images walks them
    # (rglob skipped an unreadable one unsaid; the walk names it)
    with os.scandir(folder) as entries:
        found = sorted(entry.name for entry in entries if _is_folder(entry)
                       and any(path.suffix.lower() in IMAGE_SUFFIXES for path in entries_below(Path(entry.path))))
    return ", ".join(ascii(name) for name in found[:3]) + (f" and {len(found) - 3} more" if len(found) > 3 else "")


def _is_folder(entry: os.DirEntry) -> bool:
    """Whether `entry` is a folder; False for a link that loops (ELOOP), which is no folder of images and,
    not named like an image, is ignored as other files are."""
    try:
        return entry.is_dir()
    except OSError:
        return False


def utf8_name(path: Path, name: str | None = None) -> Path:
    """`path`, refused when its name (or `name`, what a store calls it) is bytes that are no UTF-8 text (written
    in another encoding): stores and records keep image names as text, and positions.csv could not name it."""
    try:
        (path.name if name is None else name).encode("utf-8")
    except UnicodeEncodeError:
        raise VPRBenchError(f"Image {os.fsencode(path.name)!r} in {path.parent}: its name is not UTF-8 text (another "
                            "encoding's bytes); rename it.") from None
    return path


def _is_image_file(path: Path) -> bool:
    """A file to read; False for a folder named like an image; an error for a named pipe (reading
    it would hang) or a device, and for a link that leads nowhere (skipping it would drop an image unseen)."""
    return refuse_dead_link(path) if path.is_symlink() and not path.exists() else regular_file(path, "Image")


def refuse_dead_link(path: Path) -> bool:
    """False for a folder named like an image; an error for a link named like one that leads
    nowhere (or loops): skipping it would drop an image unseen."""
    if path.is_symlink() and not path.exists():
        raise VPRBenchError(f"Image {path} is a symbolic link to a missing file (or a link loop): "
                            "point it at the image or remove it.")
    return False
