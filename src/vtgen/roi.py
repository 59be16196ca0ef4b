"""Regions of interest in tactile and visual images: boxes, tiles, contact regions, markers.

Pure functions on images held as numpy ``uint8`` arrays of shape (H, W, 3), RGB. Nothing here
reads or writes files; the ROI stage does that and calls these functions.

GelSight frames carry a grid of small dark marker dots that are present everywhere, in and
out of contact. :func:`marker_mask` finds them, :func:`remove_markers` paints them out and
:func:`contact_box` ignores them when it looks for the pressed (textured) part of the gel.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import binary_fill_holes
from skimage.filters import threshold_otsu
from skimage.filters.rank import median
from skimage.morphology import footprint_rectangle


@dataclass(frozen=True)
class Box:
    """An axis-aligned pixel rectangle: top-left corner (x, y), width w and height h.

    Raises ``ValueError`` unless ``w > 0``, ``h > 0``, ``x >= 0`` and ``y >= 0``.
    """

    x: int
    y: int
    w: int
    h: int

    def __post_init__(self) -> None:
        if self.w <= 0 or self.h <= 0 or self.x < 0 or self.y < 0:
            raise ValueError(f"invalid {self}: need w > 0, h > 0, x >= 0 and y >= 0")

    def fits(self, width: int, height: int) -> bool:
        """True if the box lies wholly inside an image of ``width`` x ``height`` pixels."""
        return self.x + self.w <= width and self.y + self.h <= height


def centre_box(width: int, height: int, fraction: float = 1.0) -> Box:
    """The centred square of side ``floor(fraction * min(width, height))``.

    ``0 < fraction <= 1``; when the leftover margin is odd the extra pixel goes to the
    right/bottom. ``ValueError`` if the fraction is out of range or the side would be 0.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    side = int(np.floor(fraction * min(width, height)))
    if side <= 0:
        raise ValueError(f"fraction {fraction} of a {width}x{height} image gives an empty square")
    return Box((width - side) // 2, (height - side) // 2, side, side)


def tile_boxes(width: int, height: int, tile: int, stride: int | None = None) -> list[Box]:
    """Square tiles of side ``tile`` on a regular grid with step ``stride``, in row-major order.

    ``stride`` defaults to ``tile`` (non-overlapping tiles); a smaller stride overlaps them.
    The grid holds as many tiles as fit along each axis and is centred in the image (odd
    leftover pixel to the right/bottom). ``ValueError`` if ``tile <= 0``, ``stride <= 0`` or
    ``tile > min(width, height)``.
    """
    stride = tile if stride is None else stride
    if tile <= 0 or stride <= 0:
        raise ValueError(f"tile and stride must be positive, got tile={tile}, stride={stride}")
    if tile > min(width, height):
        raise ValueError(f"tile {tile} does not fit in a {width}x{height} image")

    def starts(length: int) -> list[int]:
        n = (length - tile) // stride + 1
        offset = (length - ((n - 1) * stride + tile)) // 2
        return [offset + i * stride for i in range(n)]

    return [Box(x, y, tile, tile) for y in starts(height) for x in starts(width)]


def _check_rgb(image: np.ndarray) -> None:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        shape = getattr(image, "shape", None)
        dtype = getattr(image, "dtype", type(image).__name__)
        raise ValueError(f"expected a uint8 RGB image of shape (H, W, 3), got shape {shape} and dtype {dtype}")


def _odd(n: float) -> int:
    return int(n) // 2 * 2 + 1


def marker_mask(frame: np.ndarray, max_dot: int | None = None) -> np.ndarray:
    """Boolean (H, W) mask of the dark marker dots of a GelSight frame.

    A dot is a small, dark, roughly round (or square) blob no wider than ``max_dot`` pixels
    (default: an eighth of the shorter image side, 32 px on a 256 px tile). Method: a 5 px
    median blur of the grey image removes fine texture; a black-hat (closing minus image,
    with an elliptical kernel larger than a dot) divided by the closing gives each pixel's
    depth relative to its surroundings, so dots in darker parts of the frame count as much
    as dots in bright ones; Otsu thresholds the depth (at least 0.2). Connected components
    that are too small (< 9 px), too large (> ``max_dot**2``), too elongated (aspect ratio
    > 3, unless cut by the image border) or too sparse (filling < 40 % of their bounding
    box) are dropped. The same is done at a second, deeper Otsu threshold computed over the
    candidates only, which separates dots from a darker region they touch; the union is
    kept. The mask is then dilated by 2 px to cover the dots' soft edges. A frame without
    dark blobs gives an all-False mask.
    """
    _check_rgb(frame)
    height, width = frame.shape[:2]
    max_dot = max(3, min(height, width) // 8) if max_dot is None else max_dot
    grey = cv2.medianBlur(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), 5)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (_odd(1.25 * max_dot),) * 2)
    closed = cv2.morphologyEx(grey, cv2.MORPH_CLOSE, kernel).astype(np.float64)
    depth = (closed - grey) / np.maximum(closed, 1)
    if depth.max() <= 0.2:  # nothing clearly darker than its surroundings
        return np.zeros((height, width), bool)
    level = max(threshold_otsu(depth), 0.2)
    deeper = max(threshold_otsu(depth[depth > level]), level)
    dots = _dot_like(depth > level, max_dot) | _dot_like(depth > deeper, max_dot)
    return cv2.dilate(dots.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))).astype(bool)


def _dot_like(candidates: np.ndarray, max_dot: int) -> np.ndarray:
    """The connected components of ``candidates`` that are shaped like marker dots."""
    height, width = candidates.shape
    count, labels, stats, _ = cv2.connectedComponentsWithStats(candidates.astype(np.uint8), connectivity=8)
    keep = np.zeros(count, bool)
    for i in range(1, count):
        x, y, w, h, area = stats[i]
        on_border = x == 0 or y == 0 or x + w == width or y + h == height
        elongated = max(w, h) > 3 * min(w, h) and not on_border
        keep[i] = 9 <= area <= max_dot**2 and not elongated and area >= 0.4 * w * h
    return keep[labels]


def remove_markers(frame: np.ndarray, radius: int = 3) -> np.ndarray:
    """A copy of ``frame`` with the marker dots of :func:`marker_mask` inpainted (Telea).

    ``radius`` is the inpainting neighbourhood in pixels. Pixels outside the mask are
    returned unchanged; the input array is not modified.
    """
    _check_rgb(frame)
    mask = marker_mask(frame).astype(np.uint8)
    if not mask.any():
        return frame.copy()
    return cv2.inpaint(np.ascontiguousarray(frame), mask, radius, cv2.INPAINT_TELEA)


def contact_box(frame: np.ndarray, min_fraction: float = 0.05, flat_level: float = 4.0, window: int = 7) -> Box:
    """Bounding box of the contact region of a GelSight frame: where the pressed gel departs from flat.

    Method: the marker dots (:func:`marker_mask`), which are everywhere, in and out of
    contact, are left out of every statistic below. The flat-gel colour is the median colour
    of a ``window``-wide strip along the frame border. Each pixel's deviation from it (root
    mean square over the three channels, in grey levels) is median-filtered over a
    ``window``-square of non-marker pixels, which suppresses noise and keeps the region's
    edges in place. Otsu's threshold (at least ``flat_level``) splits that map; the largest
    connected component of the contact side, closed and with its holes filled, gives the box.

    Fallback, by design, to the whole frame (``Box(0, 0, W, H)``) when

    - no pixel deviates by more than ``flat_level`` grey levels (no contact);
    - the background side of the split is not flat (its median exceeds ``flat_level``): the
      border itself is contact, so the frame is all contact, as ViTac tiles usually are;
    - the detected region covers less than ``min_fraction`` of the frame.

    Caveats: the background is one colour, so a strong illumination gradient across a flat
    gel would read as contact; the border strip must be mostly flat gel (a contact region
    covering most of the border makes the frame count as all contact).
    """
    _check_rgb(frame)
    height, width = frame.shape[:2]
    whole = Box(0, 0, width, height)
    valid = ~marker_mask(frame)
    border = np.ones((height, width), bool)
    border[window:-window, window:-window] = False
    if not (border & valid).any():
        return whole
    colour = frame.astype(np.float64)
    background = np.median(colour[border & valid], axis=0)
    deviation = np.sqrt(((colour - background) ** 2).mean(axis=2)).round().astype(np.uint8)
    deviation = np.where(valid, median(deviation, footprint_rectangle((window, window)), mask=valid), 0)
    values = deviation[valid]
    if values.max() <= flat_level:
        return whole
    level = max(threshold_otsu(values), flat_level)
    if np.median(values[values <= level]) > flat_level:
        return whole
    contact = (deviation > level).astype(np.uint8)
    contact = cv2.morphologyEx(contact, cv2.MORPH_CLOSE, np.ones((window, window), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(contact, connectivity=8)
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x, y, w, h = (int(v) for v in stats[best, :4])
    if binary_fill_holes(labels == best).sum() < min_fraction * width * height:
        return whole
    return Box(x, y, w, h)


def cut_tile(image: np.ndarray, box: Box, size: int) -> np.ndarray:
    """Crop ``box`` from ``image`` and resize it to a ``(size, size, 3)`` uint8 tile.

    Uses ``cv2.INTER_AREA`` when the tile is no larger than the box on either side
    (shrinking) and ``cv2.INTER_CUBIC`` otherwise (enlarging). ``ValueError`` if the box
    does not fit in the image or ``size <= 0``.
    """
    _check_rgb(image)
    height, width = image.shape[:2]
    if size <= 0:
        raise ValueError(f"tile size must be positive, got {size}")
    if not box.fits(width, height):
        raise ValueError(f"{box} does not fit in a {width}x{height} image")
    crop = image[box.y : box.y + box.h, box.x : box.x + box.w]
    if box.w == box.h == size:
        return crop.copy()
    shrinking = size <= min(box.w, box.h)
    return cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA if shrinking else cv2.INTER_CUBIC)
