"""Reading and writing images, and writing stage outputs atomically.

Every image enters the pipeline through :func:`read_rgb8`, so the conversion rules
(grayscale, 16-bit, palette, alpha) are applied the same way by every stage.
"""

from __future__ import annotations

import contextlib
from collections import deque
import errno
import hashlib
import os
import multiprocessing
import shutil
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterable, Iterator, TypeVar

import sys
from typing import TYPE_CHECKING

import cv2
import numpy as np
from PIL import Image

if TYPE_CHECKING:  # torch is imported where tiles become tensors: the stages that only read and write images start a second sooner
    import torch

IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"})
# The file formats the pipeline decodes, and the one each extension promises. Pillow reads
# many more (TGA, ICO, PCX, ...), but some of those accept almost any bytes, so random data
# named .png would be "decoded" as noise; only these are tried.
DECODED_FORMATS = ("PNG", "JPEG", "BMP", "TIFF", "WEBP")  # JPEG includes multi-picture (MPO) files
_FORMAT_OF_EXTENSION = {".jpg": "JPEG", ".jpeg": "JPEG", ".png": "PNG", ".bmp": "BMP", ".tif": "TIFF",
                        ".tiff": "TIFF", ".webp": "WEBP"}
# Largest image decoded, in pixels (Pillow's own decompression-bomb threshold, about 9459 x 9459).
# Checked explicitly after the header is read, so the limit holds in every thread.
MAX_PIXELS = 89_478_485


class ImageError(ValueError):
    """A file cannot be used as an image; the message says why."""


def display_path(path: str | Path) -> str:
    """``path`` as printable UTF-8 text: undecodable bytes of a file name appear as ``\\xff`` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def is_utf8_path(path: str | Path) -> bool:
    """True when the name can be stored as UTF-8 text (in a table, a CSV, a log line) and read back."""
    try:
        str(path).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def file_md5(path: str | Path, chunk: int = 1 << 16) -> str:
    """MD5 of a file's bytes (the content hash DVC uses too), read in 64 KiB blocks (a 1 MiB read
    allocates 1 MiB per call, per file)."""
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
    palette images are expanded, alpha is dropped; a file whose content is another format than
    its extension says (a JPEG named .png) is read and noted. Raises ImageError for a file that
    is empty, not an image, truncated, too large (over MAX_PIXELS) or otherwise undecodable,
    whatever the decoder raised.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise ImageError("symbolic link loop (too many levels of symbolic links)") from exc
        if exc.errno == errno.ENOENT and path.is_symlink():
            raise ImageError(f"broken symbolic link to {display_path(os.readlink(path))}") from exc
        raise ImageError(f"cannot read file: {exc.strerror or exc}") from exc
    if size == 0:
        raise ImageError("empty file (0 bytes)")
    try:
        with Image.open(path, formats=DECODED_FORMATS) as image:
            width, height = image.size
            if width < 1 or height < 1:
                raise ImageError(f"image has no pixels ({width}x{height})")
            if width * height > MAX_PIXELS:
                raise ImageError(f"image too large to decode safely: {width}x{height} pixels "
                                 f"(limit {MAX_PIXELS:,} pixels)")
            mode, file_format = image.mode, image.format
            tile_modes = [str(t.args) for t in getattr(image, "tile", []) if t.args]
            image.load()
            channels = len(image.getbands())
            array, note = _to_rgb8(image, mode, tile_modes, path)
    except ImageError:
        raise
    except Image.DecompressionBombError as exc:
        raise ImageError(f"image too large to decode safely: {exc}") from exc
    except MemoryError as exc:
        raise ImageError("image too large: out of memory while decoding it") from exc
    except Image.UnidentifiedImageError as exc:
        raise ImageError(f"not a decodable image: not {', '.join(DECODED_FORMATS[:-1])} or "
                         f"{DECODED_FORMATS[-1]} data") from exc
    except OSError as exc:
        text = _without_path(str(exc), path)
        if "truncated" in text.lower():
            raise ImageError(f"truncated image: {text}") from exc
        raise ImageError(f"not a decodable image: {text}") from exc
    except Exception as exc:  # noqa: BLE001 - a corrupt file can make any decoder step fail; it is the file's fault
        raise ImageError(f"not a decodable image ({type(exc).__name__}: {_without_path(str(exc), path)})") from exc
    if array.shape[0] < 1 or array.shape[1] < 1:
        raise ImageError(f"image has no pixels ({array.shape[1]}x{array.shape[0]})")
    expected = _FORMAT_OF_EXTENSION.get(path.suffix.lower())
    actual = "JPEG" if file_format == "MPO" else file_format
    if expected and actual != expected:
        note = "; ".join(n for n in (f"file holds {actual} data but is named {path.suffix}", note) if n)
    wide = mode.startswith("I;16") or mode == "I" or any(";16" in m for m in tile_modes)
    return DecodedImage(array, note, channels, 16 if wide else 8)


def _without_path(text: str, path: Path) -> str:
    """Decoder messages often repeat the file name; the caller records the path already."""
    for form in (repr(str(path)), str(path)):
        text = text.replace(form, "the file")
    return display_path(text)


def _deep_colour(path: Path, shape: tuple[int, int]) -> np.ndarray | None:
    """The 16-bit colour samples of ``path`` as RGB uint16, or None. Pillow keeps only the high
    byte of 16-bit colour images, so OpenCV decodes them (from bytes: any file name works)."""
    decoded = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None or decoded.dtype != np.uint16 or decoded.ndim != 3 or decoded.shape[:2] != shape:
        return None
    return decoded[:, :, 2::-1] if decoded.shape[2] >= 3 else None


def _to_rgb8(image: Image.Image, mode: str, tile_modes: list[str], path: Path) -> tuple[np.ndarray, str]:
    notes = []
    if any(";16" in m for m in tile_modes) and not mode.startswith("I"):
        deep = _deep_colour(path, (image.height, image.width)) if mode in ("RGB", "RGBA") else None
        if deep is not None:
            notes.append(f"16-bit {mode} scaled to 8-bit" + (", alpha dropped" if mode == "RGBA" else ""))
            return np.clip(np.rint(deep * (255.0 / 65535.0)), 0, 255).astype(np.uint8), "; ".join(notes)
        notes.append(f"16-bit {mode} reduced to 8-bit (high byte)")
    if mode in ("I;16", "I;16B", "I;16L", "I;16N", "I"):
        data = np.asarray(image, dtype=np.float64)
        if mode == "I" and not any("16" in m for m in tile_modes):
            # 32-bit integer samples: usable only when they hold 16-bit values
            if data.size and (data.min() < 0 or data.max() > 65535):
                raise ImageError(f"32-bit integer image with values in [{data.min():.0f}, {data.max():.0f}]: "
                                 f"its value range is unknown")
            notes.append("32-bit integer grayscale (values within 16 bits) scaled to 8-bit and replicated to RGB")
        else:
            notes.append(f"16-bit grayscale ({mode}) scaled to 8-bit and replicated to RGB")
        data = np.clip(np.rint(data * 255.0 / 65535.0), 0, 255).astype(np.uint8)
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


def _pool_worker(parent: int) -> None:
    """Process-pool initializer: the pool's processes are the parallelism, so OpenCV and torch
    run one thread each inside them; and a worker ends when its parent is gone (a stage killed by
    SIGKILL cannot stop its pool, whose workers would otherwise wait for tasks for ever). The watchdog
    starts first, so that a worker stuck in its first OpenCV call still ends with its parent."""
    threading.Thread(target=_exit_with, args=(parent,), daemon=True).start()
    cv2.setNumThreads(1)
    os.environ["OMP_NUM_THREADS"] = "1"  # torch imported later in this worker reads it
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)


def _exit_with(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _map_batch(func: Callable[[T], R], batch: list[T]) -> list[R]:
    return [func(item) for item in batch]


def _batches(items: Iterable[T], size: int) -> Iterator[list[T]]:
    batch: list[T] = []
    for item in items:
        batch.append(item)
        if len(batch) == size:
            yield batch
            batch = []
    if batch:
        yield batch


def _results(future, desc: str) -> list:
    try:
        return future.result()
    except BrokenProcessPool as exc:
        raise RuntimeError(f"{desc or 'stream_map'}: a worker process ended abruptly (killed by a signal, or out of "
                           f"memory)") from exc


def stream_map(func: Callable[[T], R], items: Iterable[T], workers: int, total: int | None = None, desc: str = "",
               progress: bool = False, window: int | None = None, processes: bool = False,
               batch: int = 8) -> Iterator[R]:
    """``func`` over ``items`` on ``workers`` threads (or processes), results in input order, streamed.

    At most ``window`` tasks (default 4 per worker) are taken from ``items`` and not yet handed
    back, so memory is bounded by the window, not by the number of items: ``items`` may be a lazy
    iterator and is read only as results are consumed (``Executor.map`` would submit every item at
    once and keep a future per item).
    If ``func`` raises, the exception is raised here and the tasks not started are cancelled.
    Threads suffice where the work is mostly decoding, resizing and encoding, which release the
    GIL. ``processes=True`` is for work with many small numpy steps, which hold it: ``func`` (a
    module-level function), its items and results must then pickle; the processes are forked where
    the platform allows, and each task is a ``batch`` of items, so the cost of handing a task to
    another process (a fraction of a millisecond) is paid once per batch.
    """
    workers = max(1, int(workers))
    window = max(workers, window or 4 * workers)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=desc, unit="img")
    opencv_threads = cv2.getNumThreads()
    if processes and workers > 1:
        # OpenCV's thread pool is shut while the pool lives: a process forked while that pool runs hangs
        # in its first OpenCV call (seen with the roi stage's workers), and the workers are the parallelism
        cv2.setNumThreads(1)
        method = "fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn"
        executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context(method),
                                       initializer=_pool_worker, initargs=(os.getpid(),))
        tasks = ((_map_batch, func, chunk) for chunk in _batches(items, max(1, int(batch))))
    else:
        executor = ThreadPoolExecutor(max_workers=workers)
        tasks = ((_map_batch, func, [item]) for item in items)
    try:
        yield from _stream(executor, tasks, window, desc, bar)
    finally:
        cv2.setNumThreads(opencv_threads)


def _stream(executor, tasks: Iterator, window: int, desc: str, bar) -> Iterator:
    """:func:`stream_map`'s loop: submit ``tasks`` to ``executor`` keeping at most ``window`` in flight,
    and yield their results in order."""
    pending: deque = deque()
    with executor as pool:
        try:
            for task in tasks:
                pending.append(pool.submit(*task))
                if len(pending) >= window:
                    for result in _results(pending.popleft(), desc):
                        yield result
                        if bar is not None:
                            bar.update()
            while pending:
                for result in _results(pending.popleft(), desc):
                    yield result
                    if bar is not None:
                        bar.update()
        finally:
            # shutdown's own cancel, not Future.cancel: a future cancelled by hand just after its submit can hang
            # the shutdown of a process pool for ever (CPython gh-94440, fixed in 3.11.3 and 3.12)
            pool.shutdown(wait=True, cancel_futures=True)
            if bar is not None:
                bar.close()


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB array as PNG."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"{path}: expected (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
    Image.fromarray(rgb, "RGB").save(path, compress_level=1)


# errno values that mean "this cannot be written here", whatever the stage was doing
_NO_SPACE = {errno.ENOSPC, errno.EDQUOT}
_NOT_WRITABLE = {errno.EACCES, errno.EPERM, errno.EROFS}


class OutputDirError(OSError):
    """The output folder cannot be created or replaced; the message names it and says why."""


def check_output_dir(out_dir: str | Path) -> Path:
    """Make sure ``out_dir`` can be written (creating its parent), or raise OutputDirError saying why.

    Stages that work long before they write call this first, so a bad ``--out`` fails at once.
    """
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise OutputDirError(errno.ENOTDIR, "exists and is a file, not an output folder", str(out_dir))
    for parent in (out_dir.parent, *out_dir.parent.parents):
        if parent.exists() and not parent.is_dir():
            raise OutputDirError(errno.ENOTDIR, f"cannot create the output folder: {display_path(parent)} is a file",
                                 str(out_dir))
        if parent.is_dir():
            break
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputDirError(exc.errno, f"cannot create the output folder's parent: {describe_os_error(exc)}",
                             str(out_dir)) from exc
    if not os.access(out_dir.parent, os.W_OK | os.X_OK):
        raise OutputDirError(errno.EACCES, f"cannot write the output folder: {display_path(out_dir.parent)} "
                                           f"is not writable", str(out_dir))
    return out_dir


@contextlib.contextmanager
def atomic_output_dir(out_dir: str | Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``out_dir``; on success it replaces ``out_dir`` in one rename.

    A stage killed part-way leaves the previous ``out_dir`` (or none) and a ``.tmp`` sibling
    that the next run removes; never a half-written ``out_dir``. The folder is checked before
    any work starts (:func:`check_output_dir`). A write error without a file name (a full disk
    seen by a writer that does not know its path) is given ``out_dir`` as its file name.
    """
    out_dir = check_output_dir(out_dir)
    tmp = out_dir.with_name(f".{out_dir.name}.tmp")
    _remove(tmp)  # left by a run that was killed
    tmp.mkdir()
    try:
        yield tmp
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)  # frees the space a full disk needs back
        if isinstance(exc, OSError) and exc.filename is None and exc.errno in _NO_SPACE | _NOT_WRITABLE:
            exc.filename = str(out_dir)
        raise
    old = out_dir.with_name(f".{out_dir.name}.old")
    _remove(old)
    if out_dir.exists():
        out_dir.rename(old)
    tmp.rename(out_dir)
    shutil.rmtree(old, ignore_errors=True)


def _remove(path: Path) -> None:
    if path.is_symlink() or path.is_file():
        path.unlink()
    else:
        shutil.rmtree(path, ignore_errors=True)


def describe_os_error(exc: OSError) -> str:
    """One line saying what happened and where, for an OSError that reached the command line.

    A full disk, a folder that cannot be written and a path through a file get a sentence that
    names the path and what to do; anything else is ``<path>: <system message>``.
    """
    where = display_path(exc.filename) if exc.filename is not None else None
    if isinstance(exc, OutputDirError):
        return f"{where}: {exc.strerror}"
    if exc.errno in _NO_SPACE:
        kind = "disk quota exceeded" if exc.errno == errno.EDQUOT else "no space left on device (disk full)"
        place = f" while writing {where}" if where else ""
        return f"{kind}{place}; free some space or write to another disk, then run again"
    if exc.errno == errno.EROFS:
        return f"{where or 'output'}: read-only file system; write the outputs to a writable disk"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"{where or 'a file'}: permission denied; check the folder's permissions or choose another location"
    if exc.errno == errno.ENOTDIR:
        return f"{where}: a part of this path is a file, not a folder"
    text = exc.strerror or str(exc)
    return f"{where}: {text}" if where else display_path(text)


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


def read_tiles(paths: list[str], size: int, root: Path = Path("."), remedy: str = "rerun the roi stage") -> torch.Tensor:
    """Read 8-bit RGB tiles (``root / path``) into a uint8 N x 3 x size x size tensor, resizing (area/bilinear)
    when needed. A missing, truncated, corrupt or non-RGB file, or tiles of different sizes, raise ValueError
    naming the file and ``remedy`` (the stage that writes these images)."""
    import torch

    if not paths:
        return torch.zeros((0, 3, size, size), dtype=torch.uint8)
    arrays = []
    for path in paths:
        arrays.append(_read_tile(Path(root) / path, remedy))
        if arrays[-1].shape != arrays[0].shape:
            raise ValueError(f"{display_path(Path(root) / path)}: tile is {arrays[-1].shape[1]}x{arrays[-1].shape[0]}, "
                             f"but {display_path(Path(root) / paths[0])} is {arrays[0].shape[1]}x{arrays[0].shape[0]}; "
                             f"{remedy}")
    return resize_tiles(torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous(), size)


def resize_tiles(batch: torch.Tensor, size: int) -> torch.Tensor:
    """A uint8 N x 3 x H x W batch at ``size`` x ``size``: unchanged when it is already, else area-resized
    when shrinking and bilinear when growing, rounded back to uint8."""
    import torch
    import torch.nn.functional as F

    if batch.shape[-1] != size or batch.shape[-2] != size:
        batch = F.interpolate(batch.float(), size=(size, size), mode="area" if batch.shape[-1] > size else "bilinear",
                              align_corners=None if batch.shape[-1] > size else False)
        batch = batch.round().clamp(0, 255).to(torch.uint8)
    return batch


def _read_tile(path: Path, remedy: str) -> np.ndarray:
    """One tile as an (H, W, 3) uint8 array, or ValueError naming ``path``, what is wrong and ``remedy``."""
    where = display_path(path)
    if not path.is_file():
        raise ValueError(f"{where}: tile not found ({'a folder' if path.is_dir() else 'no such file'}); {remedy}")
    try:
        with Image.open(path, formats=DECODED_FORMATS) as image:
            mode = image.mode
            image.load()
            array = np.asarray(image)
    except Image.UnidentifiedImageError as exc:
        raise ValueError(f"{where}: not a decodable image; {remedy}") from exc
    except OSError as exc:
        text = _without_path(str(exc), path)
        kind = "truncated tile" if "truncated" in text.lower() else "corrupt tile"
        raise ValueError(f"{where}: {kind} ({text}); {remedy}") from exc
    except Exception as exc:  # noqa: BLE001 - a corrupt file can make any decoder step fail; it is the file's fault
        raise ValueError(f"{where}: corrupt tile ({type(exc).__name__}: {_without_path(str(exc), path)}); "
                         f"{remedy}") from exc
    if mode != "RGB":
        raise ValueError(f"{where}: tile is {mode}, expected 8-bit RGB; {remedy}")
    return array


def read_for_roi(path: str | Path) -> np.ndarray:
    """The image at ``path`` as (H, W) grey or (H, W, 3) RGB uint8: the pixels of ``read_rgb8`` (grey
    replicated to RGB there). Baseline 8-bit grey and colour JPEGs are decoded by OpenCV (3-4 times
    faster than Pillow plus the RGB copy on 640x480 grey frames); anything else, or a file OpenCV
    decodes to another shape or type, goes through ``read_rgb8`` and its errors."""
    if Path(path).suffix.lower() in {".jpg", ".jpeg"}:
        try:
            data = np.fromfile(path, np.uint8)
        except OSError:
            data = None
        if data is not None and data[:3].tobytes() == b"\xff\xd8\xff":
            decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
            if decoded is not None and decoded.dtype == np.uint8:
                if decoded.ndim == 2:
                    return decoded
                if decoded.ndim == 3 and decoded.shape[2] == 3:
                    return cv2.cvtColor(decoded, cv2.COLOR_BGR2RGB)
    return read_rgb8(path).rgb
