"""One reader for every mask the harness is given: `segment --mask`, datasets' ground truth,
and the label maps `sagonline score` compares.

A mask file is read as what it is, or refused with what was seen (channels, bit depth and the
number of distinct values):
- a **binary** mask: any two levels, anti-aliased or saved as JPEG, thresholded at mid-level
  (the pixels between the levels lie on the edge between them): object 1 on background 0;
- a **label map**: one channel of integer ids (8- or 16-bit, or a palette PNG's indices,
  which are always ids), 0 = background, ids below `max_labels` (256 by default);
- **RGBA**: the alpha channel, when the colour channels are constant (a cut-out); with varying
  colour and opaque alpha, the colour channels as below;
- **RGB**: read as grey only when its three channels are equal; a colour image is refused.

`mode` says what a caller accepts: "auto" (binary or label map, decided by the file), "binary"
(always thresholded: at `threshold` when given, else mid-level), "ids" (a label map only; a
two-level file keeps its two values).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from sagonline.core.errors import DatasetError

MAX_LABELS = 256
MODES = ("auto", "binary", "ids")


class MaskFileError(DatasetError):
    """A mask file that cannot be read as a mask; names the file and what was seen."""


@dataclass(frozen=True)
class MaskFile:
    """A mask as read: labels (H, W) uint8 or uint16, the file's own width (0 background; a
    1296x972 mask is 1.3 MB, where int64 held 10 MB), how it was read ("binary" or
    "label map") and what the file held."""

    labels: np.ndarray
    kind: str
    seen: str


def read_mask(
    path: str | Path,
    mode: str = "auto",
    *,
    max_labels: int = MAX_LABELS,
    threshold: float | None = None,
    colour: str = "refuse",
    max_pixels: int | None = None,
) -> MaskFile:
    """Read one mask file (see the module docstring); MaskFileError names the file.
    colour="max" reads a colour image as the maximum of its channels (a dataset whose binary
    masks are drawn in colour) instead of refusing it. max_pixels: the most pixels the file may
    hold, checked on its header before decoding (default `io.images.MAX_IMAGE_PIXELS`; a
    caller that knows the view's size passes that)."""
    path = Path(path)
    if mode not in MODES:
        raise ValueError(f"mask mode {mode!r} is not one of {MODES}")
    image, seen = _load(path, max_pixels)
    if mode == "auto" and seen.startswith("a palette") and len(distinct_values(image)) > 2:
        mode = "ids"  # a palette's indices are label ids
    try:
        plane = _one_plane(image, path, seen)
    except MaskFileError:
        if colour != "max":
            raise
        plane = image[..., :3].max(axis=2)
    return decide(plane, path, seen, mode, max_labels, threshold)


def read_mask_colours(
    path: str | Path, max_pixels: int | None = None
) -> np.ndarray:  # [H, W, 3] uint8 RGB
    """A mask drawn in colours (a dataset's palette of label colours) as (H, W, 3) RGB, read
    by the same loader as `read_mask` (the same checks): MaskFileError names the file."""
    path = Path(path)
    image, seen = _load(path, max_pixels)
    if image.ndim == 2:
        image = image[..., None].repeat(3, axis=2)
    if image.dtype != np.uint8 or image.shape[2] not in (3, 4):
        raise MaskFileError(f"{path}: {seen}; a colour mask is 8-bit RGB (or RGBA)")
    return np.ascontiguousarray(image[..., 2::-1])  # BGR(A) -> RGB


def decide(
    plane: np.ndarray,
    path: Path | str,
    seen: str,
    mode: str = "auto",
    max_labels: int = MAX_LABELS,
    threshold: float | None = None,
) -> MaskFile:
    """A single (H, W) plane of integer values -> the mask, by the rules of `read_mask`."""
    values = distinct_values(plane)
    seen = f"{seen}, {len(values)} distinct value{'s' if len(values) != 1 else ''}"
    if mode == "binary" or (mode == "auto" and _binary(plane, values)):
        lo, hi = int(values[0]), int(values[-1])
        if threshold is None:
            if len(values) == 1:
                return MaskFile((plane > 0).view(np.uint8), "binary", seen)
            threshold = (lo + hi) / 2
        elif 0 < hi <= threshold:
            raise MaskFileError(
                f"{path}: its values ({lo}..{hi}, {seen}) all lie at or below the threshold "
                f"{threshold:g}: it would read as empty"
            )
        return MaskFile((plane > threshold).view(np.uint8), "binary", seen)
    top = int(values[-1])
    if values[0] < 0 or top >= max_labels:
        raise MaskFileError(
            f"{path}: a label map's ids must lie in [0, {max_labels}), this one holds "
            f"{int(values[0])}..{top} ({seen}); a binary mask needs exactly two levels"
            + (", or anti-aliased edges between them" if mode == "auto" else "")
        )
    return MaskFile(np.ascontiguousarray(plane), "label map", seen)  # a channel: its own copy


def distinct_values(plane: np.ndarray) -> np.ndarray:  # [K] of plane's dtype, ascending
    """`np.unique(plane)`; for 8- and 16-bit planes (every mask file) from OpenCV's histogram,
    which counts a 1296x972 mask in 0.3 ms where the sort takes 6."""
    levels = {np.dtype(np.uint8): 256, np.dtype(np.uint16): 65536}.get(plane.dtype)
    if levels is None or plane.ndim != 2 or not plane.size:
        return np.unique(plane)
    counts = cv2.calcHist([np.ascontiguousarray(plane)], [0], None, [levels], [0, levels])
    return np.flatnonzero(counts.ravel()).astype(plane.dtype)


def _load(path: Path, max_pixels: int | None = None) -> tuple[np.ndarray, str]:
    """The file's pixels as stored (palette PNGs as their indices) and a description; its
    size is checked on the header first (`io.images.image_size`)."""
    from sagonline.scene.io.images import ImageFileError, image_size

    try:
        with open(path, "rb") as f:
            head = f.read(26)
    except OSError as exc:
        raise MaskFileError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    try:
        image_size(path, max_pixels)
    except ImageFileError as exc:
        raise MaskFileError(str(exc)) from None
    # A palette PNG (IHDR colour type 3): its indices are the labels. Read with PIL's PNG
    # reader directly (`Image.open` may be patched by other packages to fetch plug-ins).
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) > 25 and head[25] == 3:
        from PIL import PngImagePlugin

        try:
            with PngImagePlugin.PngImageFile(str(path)) as im:
                return np.asarray(im), f"a palette image of {im.size[0]}x{im.size[1]}"
        except (OSError, SyntaxError, ValueError) as exc:
            raise MaskFileError(f"{path}: not a readable image ({exc})") from None
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise MaskFileError(f"{path}: not a readable image")
    channels = 1 if image.ndim == 2 else image.shape[2]
    depth = {np.dtype(np.uint8): 8, np.dtype(np.uint16): 16}.get(image.dtype)
    if depth is None:
        raise MaskFileError(f"{path}: {image.dtype} pixels; a mask is 8- or 16-bit")
    h, w = image.shape[:2]
    return image, f"{channels} channel{'s' if channels > 1 else ''}, {depth}-bit, {w}x{h}"


def _one_plane(image: np.ndarray, path: Path, seen: str) -> np.ndarray:
    """The one channel a mask's values are in (see the module docstring)."""
    if image.ndim == 2:
        return image
    channels = image.shape[2]
    if channels == 2:  # grey + alpha
        colour, alpha = image[..., :1], image[..., 1]
    elif channels == 4:  # BGRA
        colour, alpha = image[..., :3], image[..., 3]
    else:
        colour, alpha = image[..., :3], None
    flat = colour.reshape(-1, colour.shape[-1])
    if alpha is not None and (flat == flat[0]).all():
        return alpha  # a cut-out: the colour is constant, the alpha is the mask
    if (colour == colour[..., :1]).all():
        return colour[..., 0]  # grey stored as colour
    raise MaskFileError(
        f"{path}: a colour image ({seen}, {len(np.unique(flat, axis=0))} distinct colours); a "
        "mask is one channel (binary or label ids), or RGBA whose alpha is the mask"
    )


def _binary(plane: np.ndarray, values: np.ndarray, edge_px: int = 8) -> bool:
    """Two levels, or two levels with a few pixels in between that all lie near the edge
    between them (anti-aliasing; JPEG's ringing stays within its 8x8 blocks): thresholded at
    mid-level. In-between values that fill regions of their own make a label map."""
    if len(values) <= 2:
        return True
    lo, hi = values[0], values[-1]
    between = (plane != lo) & (plane != hi)
    fg = (plane > (float(lo) + float(hi)) / 2).astype(np.uint8)
    kernel = np.ones((2 * edge_px + 1, 2 * edge_px + 1), np.uint8)
    edge = cv2.dilate(fg, kernel) != cv2.erode(fg, kernel)
    return bool(edge[between].mean() >= 0.99)


__all__ = [
    "MAX_LABELS",
    "MaskFile",
    "MaskFileError",
    "decide",
    "distinct_values",
    "read_mask",
    "read_mask_colours",
]
