"""Decoding the listed images: each file read once into its manifest row and near-duplicate thumbnail.

8-bit greyscale and RGB files whose content matches their extension are decoded once with Pillow
without the RGB expansion (the conversion note is the one :func:`vtgen.io.images.read_rgb8` would
give); every other file goes through ``read_rgb8``, whose error becomes the quarantine reason.
"""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import numpy as np
from PIL import Image

from vtgen.core.grouping import grey_thumbnail
from vtgen.io.dataset_listing import quarantine_row
from vtgen.io.images import DECODED_FORMATS, ImageError, MAX_PIXELS, read_rgb8
from vtgen.io.images import _FORMAT_OF_EXTENSION  # the format each extension promises, as read_rgb8 checks it
from vtgen.io.layouts import Candidate


def _decode_fast(data: bytes, path: str) -> tuple[np.ndarray, str, int, int] | None:
    """(array, note, channels, bit depth) for an 8-bit L or RGB file whose format matches its
    extension, decoded once without expanding grey to RGB; None for anything else (read_rgb8 decides)."""
    expected = _FORMAT_OF_EXTENSION.get(Path(path).suffix.lower())
    try:
        with Image.open(io.BytesIO(data), formats=DECODED_FORMATS) as image:
            width, height = image.size
            if (image.mode not in ("L", "RGB") or image.format != expected or not 1 <= width * height <= MAX_PIXELS
                    or any(";16" in str(t.args) for t in getattr(image, "tile", []) if t.args)):
                return None
            mode = image.mode
            image.load()
            array = np.asarray(image)
    except Exception:  # noqa: BLE001 - read_rgb8 gives the reason
        return None
    if mode == "L":
        return array, "grayscale (L) replicated to RGB", 1, 8
    return array, "", 3, 8


def inspect_candidate(candidate: Candidate) -> dict:
    """Decode one candidate fully; a manifest row (plus its ``thumb``) or a quarantine row (key 'reason')."""
    try:
        with open(candidate.path, "rb") as handle:
            data = handle.read()
    except OSError:
        data = None  # read_rgb8 names the problem (loop, dangling link, permission)
    fast = _decode_fast(data, candidate.path) if data else None
    try:
        if fast is None:
            image = read_rgb8(candidate.path)
            fast = image.rgb, image.note, image.channels, image.bit_depth
            if data is None:
                raise OSError("file could not be read")
    except ImageError as exc:
        return quarantine_row(candidate.path, candidate.cls, candidate.modality, str(exc))
    except OSError as exc:
        return quarantine_row(candidate.path, candidate.cls, candidate.modality,
                              f"cannot read file: {exc.strerror or exc}")
    array, note, channels, bit_depth = fast
    return {
        "path": candidate.path, "md5": hashlib.md5(data).hexdigest(), "modality": candidate.modality,
        "class": candidate.cls, "split": candidate.split, "source": candidate.source, "group": "",
        "pair_key": candidate.pair_key, "width": array.shape[1], "height": array.shape[0], "channels": channels,
        "bit_depth": bit_depth, "note": "; ".join(n for n in (candidate.note, note) if n),
        "instance": candidate.instance, "session": candidate.session, "thumb": grey_thumbnail(array),
    }
