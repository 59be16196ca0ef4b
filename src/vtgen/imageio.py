"""Reading and writing images, and writing stage outputs atomically.

Every image enters the pipeline through :func:`read_rgb8`, so the conversion rules
(grayscale, 16-bit, palette, alpha) are applied the same way by every stage.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

import cv2
import numpy as np
from PIL import Image

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"})


class ImageError(ValueError):
    """A file cannot be used as an image; the message says why."""


def file_md5(path: str | Path, chunk: int = 1 << 20) -> str:
    """MD5 of a file's bytes (the content hash DVC uses too)."""
    digest = hashlib.md5()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class DecodedImage:
    """An image as the pipeline uses it, and what the file held."""

    rgb: np.ndarray      # (H, W, 3) uint8
    note: str            # the conversion applied, "" when the file was 8-bit RGB
    channels: int        # channels in the file (before conversion)
    bit_depth: int       # bits per sample in the file (8 or 16)


def read_rgb8(path: str | Path) -> DecodedImage:
    """Decode ``path`` fully into an (H, W, 3) uint8 RGB array.

    Returns the array with a note describing any conversion:
    grayscale is replicated to three channels, 16-bit samples are scaled by 255/65535,
    palette images are expanded, alpha is dropped. Raises ImageError for a file that is
    empty, not an image, truncated or otherwise undecodable.
    """
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            raise ImageError("empty file (0 bytes)")
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                mode = image.mode
                tile_modes = [str(t.args) for t in getattr(image, "tile", []) if t.args]
                image.load()
                channels = len(image.getbands())
                array, note = _to_rgb8(image, mode, tile_modes)
    except ImageError:
        raise
    except (Image.DecompressionBombError, Image.DecompressionBombWarning) as exc:
        raise ImageError(f"image too large to decode safely: {exc}") from exc
    except OSError as exc:
        text = str(exc)
        if "truncated" in text.lower():
            raise ImageError(f"truncated image: {text}") from exc
        raise ImageError(f"not a decodable image: {text}") from exc
    except (ValueError, SyntaxError) as exc:
        raise ImageError(f"not a decodable image: {exc}") from exc
    if array.shape[0] < 1 or array.shape[1] < 1:
        raise ImageError(f"image has no pixels ({array.shape[1]}x{array.shape[0]})")
    wide = mode.startswith("I;16") or mode == "I" or any(";16" in m for m in tile_modes)
    return DecodedImage(array, note, channels, 16 if wide else 8)


def _to_rgb8(image: Image.Image, mode: str, tile_modes: list[str]) -> tuple[np.ndarray, str]:
    notes = []
    if any(";16" in m for m in tile_modes) and mode == "RGB":
        notes.append("16-bit RGB scaled to 8-bit")
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        data = np.asarray(image, dtype=np.float64)
        data = np.clip(np.rint(data * 255.0 / 65535.0), 0, 255).astype(np.uint8)
        notes.append(f"16-bit grayscale ({mode}) scaled to 8-bit and replicated to RGB")
        return np.repeat(data[:, :, None], 3, axis=2), "; ".join(notes)
    if mode == "F":
        raise ImageError("floating-point image (mode F): its value range is unknown")
    if mode in ("L", "1"):
        notes.append(f"grayscale ({mode}) replicated to RGB")
    elif mode == "LA":
        notes.append("grayscale with alpha: alpha dropped, replicated to RGB")
    elif mode == "P":
        notes.append("palette image expanded to RGB")
    elif mode in ("RGBA", "RGBa", "PA"):
        notes.append("alpha channel dropped")
    elif mode == "CMYK":
        notes.append("CMYK converted to RGB")
    elif mode not in ("RGB",):
        notes.append(f"mode {mode} converted to RGB")
    rgb = image.convert("RGB") if mode != "RGB" else image
    return np.array(rgb, dtype=np.uint8), "; ".join(notes)


T = TypeVar("T")
R = TypeVar("R")


def map_images(func: Callable[[T], R], items: Iterable[T], total: int, workers: int, desc: str,
               progress: bool = True) -> Iterator[R]:
    """``func`` over ``items`` on ``workers`` threads, results in order, with a tqdm bar.

    Threads suffice: image decoding, resizing and encoding release the GIL.
    """
    with ThreadPoolExecutor(max_workers=workers) as pool:
        results = pool.map(func, items, chunksize=16)
        if progress:
            from tqdm import tqdm

            results = tqdm(results, total=total, desc=desc, unit="img")
        yield from results


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB array as PNG."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    Image.fromarray(rgb, "RGB").save(path, compress_level=1)


@contextlib.contextmanager
def atomic_output_dir(out_dir: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``out_dir``; on success it replaces ``out_dir`` in one rename.

    A stage killed part-way leaves the previous ``out_dir`` (or none) and a ``.tmp`` sibling
    that the next run removes; never a half-written ``out_dir``.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    if not os.access(out_dir.parent, os.W_OK):
        raise PermissionError(f"{out_dir.parent}: output directory is not writable")
    tmp = out_dir.with_name(f".{out_dir.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = out_dir.with_name(f".{out_dir.name}.old")
    shutil.rmtree(old, ignore_errors=True)
    if out_dir.exists():
        out_dir.rename(old)
    tmp.rename(out_dir)
    shutil.rmtree(old, ignore_errors=True)


def labelled_sheet(rows: list[tuple[str, list[list[np.ndarray | None]]]], titles: list[str], per_group: int,
                   side: int = 96) -> np.ndarray:
    """A contact sheet for a person to look at: one row per ``(label, groups)``, each group holding up
    to ``per_group`` RGB images shown at ``side`` px under its title; ``None`` cells are grey."""
    label_w, header = 120, 24
    sheet = np.full((header + side * len(rows), label_w + len(titles) * per_group * side, 3), 255, np.uint8)
    text = dict(fontFace=cv2.FONT_HERSHEY_SIMPLEX, fontScale=0.45, color=(0, 0, 0), thickness=1, lineType=cv2.LINE_AA)
    for g, title in enumerate(titles):
        cv2.putText(sheet, title, (label_w + g * per_group * side + 4, 16), **text)
    for r, (label, groups) in enumerate(rows):
        cv2.putText(sheet, str(label)[:14], (4, header + r * side + side // 2), **text)
        for g, images in enumerate(groups):
            for c, image in enumerate(images[:per_group]):
                cell = np.full((side, side, 3), 200, np.uint8) if image is None else cv2.resize(
                    image, (side, side), interpolation=cv2.INTER_NEAREST)
                x = label_w + (g * per_group + c) * side
                sheet[header + r * side:header + (r + 1) * side, x:x + side] = cell
    return sheet
