"""Images as they are read: which files are images, their size from the header before any
pixel is decoded (a 93 KB PNG can hold 768 million pixels), the one RGB reader (whole files
only: a truncated JPEG is refused, not padded), and nearest-neighbour resizing of label maps
(labels are never interpolated)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from sagonline.core.errors import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")
# The most pixels one image file may hold before it is decoded: 100 million (a 10,000 x 10,000
# photograph); SAGONLINE_MAX_IMAGE_PIXELS raises it. Readers that know the size they expect
# (a view's mask, a prediction beside its ground truth) pass a tighter ceiling.
MAX_IMAGE_PIXELS = int(os.environ.get("SAGONLINE_MAX_IMAGE_PIXELS", 100_000_000))


class ImageFileError(DatasetError):
    """An image file that cannot be read as one: names the file and what is wrong."""


def open_image(path: Path):
    """PIL's image of `path`, its header read and no pixel decoded, through the reader of the
    format its first bytes name (PNG, JPEG, BMP, TIFF, WebP): never through `Image.open`,
    which other packages (ultralytics among them) replace with one of their own. Anything else
    is not an image."""
    from PIL import BmpImagePlugin, JpegImagePlugin, PngImagePlugin, TiffImagePlugin

    with open(path, "rb") as f:
        magic = f.read(12)
    if magic.startswith(b"\x89PNG\r\n\x1a\n"):
        return PngImagePlugin.PngImageFile(str(path))
    if magic.startswith(b"\xff\xd8"):
        return JpegImagePlugin.JpegImageFile(str(path))
    if magic.startswith(b"BM"):
        return BmpImagePlugin.BmpImageFile(str(path))
    if magic[:4] in (b"II*\x00", b"MM\x00*"):
        return TiffImagePlugin.TiffImageFile(str(path))
    if magic[:4] == b"RIFF" and magic[8:12] == b"WEBP":
        from PIL import WebPImagePlugin

        return WebPImagePlugin.WebPImageFile(str(path))
    raise ImageFileError(f"{path}: not a readable image (not PNG, JPEG, BMP, TIFF or WebP)")


def image_size(path: str | Path, max_pixels: int | None = None) -> tuple[int, int]:
    """(width, height) from the file's header, no pixel decoded; ImageFileError when the file
    is not an image or holds more than `max_pixels` (default MAX_IMAGE_PIXELS)."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    ceiling = MAX_IMAGE_PIXELS if max_pixels is None else max_pixels
    try:
        with open_image(path) as im:
            w, h = im.size
    except Image.DecompressionBombError as exc:
        raise ImageFileError(
            f"{path}: exceeds the ceiling of {ceiling:,} pixels (refused before decoding: {exc})"
        ) from None
    except ImageFileError:
        raise
    except (UnidentifiedImageError, SyntaxError, ValueError) as exc:
        raise ImageFileError(f"{path}: not a readable image ({exc})") from None
    except OSError as exc:
        raise ImageFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if w * h > ceiling:
        raise ImageFileError(
            f"{path}: {w}x{h} = {w * h:,} pixels exceeds the ceiling of {ceiling:,} for this "
            "file (refused before decoding; SAGONLINE_MAX_IMAGE_PIXELS raises the general one)"
        )
    return w, h


def read_rgb(path: str | Path, max_pixels: int | None = None) -> np.ndarray:  # [H, W, 3] uint8
    """An image file as RGB uint8, its size checked first (`image_size`); a truncated or
    damaged file is refused naming it (it was read with its missing part grey)."""
    path = Path(path)
    image_size(path, max_pixels)
    try:
        with open_image(path) as im:
            im.load()
            return np.asarray(im.convert("RGB"))
    except (OSError, SyntaxError, ValueError) as exc:
        raise ImageFileError(f"{path}: a damaged or truncated image ({exc})") from None


def list_images(folder: str | Path) -> list[Path]:
    folder = Path(folder)
    return sorted(p for p in folder.iterdir() if p.suffix in IMAGE_SUFFIXES)


# Which source pixel a nearest-neighbour resize reads for each target pixel: the one under its
# centre (floor((i + 0.5) H / H'), OpenCV's INTER_NEAREST_EXACT, the same pixels as PIL's
# nearest), or the one under its top-left corner (floor(i H / H'), OpenCV's INTER_NEAREST, which
# draws a shrunk mask half a target pixel right and down). Protocol version 2 reads centres;
# version 1 read corners, and re-scoring its runs still does (docs/datasets.md).
NEAREST_SAMPLING = {"centre": cv2.INTER_NEAREST_EXACT, "corner": cv2.INTER_NEAREST}


def resize_nearest(
    mask: np.ndarray, shape: tuple[int, int], sampling: str = "centre"
) -> np.ndarray:
    """(H, W) label map -> `shape` (H', W') by nearest neighbour, dtype kept; `sampling`: a
    key of NEAREST_SAMPLING (the default keeps a mask in its place at any scale)."""
    if mask.shape == tuple(shape):
        return mask
    return cv2.resize(
        mask.astype(np.int32), (shape[1], shape[0]), interpolation=NEAREST_SAMPLING[sampling]
    ).astype(mask.dtype)
