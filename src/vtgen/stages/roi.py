"""ROI stage: cut every manifest image into square tiles at the model resolution.

Writes ``tiles/``, ``tiles.parquet`` and ``preview.png`` (visual and tactile tiles per class).

For each image a *region* is chosen first: for tactile frames the GelSight contact region
(``roi.tactile_box``: ``auto`` detection, ``full`` frame, or a fixed ``[x, y, w, h]``), for
visual images the whole photo. Inside the region, ``roi.visual_crop`` cuts one centred square
(``centre``) or a grid of squares (``tiles``) whose side is ``roi.crop_fraction`` of the
region's shorter side; each crop is resized to ``roi.size``. The same crop rule applies to
both modalities, so aligned data (equal regions) gives aligned tiles with equal boxes.
With ``roi.remove_markers`` the GelSight marker dots are painted out of the tactile tiles
(:func:`vtgen.roi.cut_tiles_without_markers`: inpainted around each crop only, at the tile's
resolution); with ``tactile_box: auto`` the whole frame is cleaned first, as contact detection
looks at all of it.

An image too small for the centre crop (``crop_fraction`` of its shorter side is under one
pixel) gives no tile; it is listed with the reason under ``skipped`` in ``summary.json``.
Images are read, cut and written one per worker thread at a time, with at most a few images per
worker in flight (:func:`vtgen.imageio.stream_map`); the manifest is read row by row and each
image's tiles are written before the next image is read. Only the tile table is kept in memory,
built column by column: the tile's file name and box, and the position of its manifest row, whose
text columns are copied once at the end.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from vtgen.io.images import atomic_output_dir, ImageError, labelled_sheet, read_rgb8, stream_map, write_png
from vtgen.io.tables import read_table
from vtgen.core.roi import crop_boxes, image_tiles, tactile_region  # noqa: F401 - crop_boxes, tactile_region: re-exported
from vtgen.io.tables import TILE_COLUMNS

MANIFEST_NEEDS = ["path", "class", "modality", "split", "source", "group", "pair_key", "width", "height"]


# The tile table's columns taken from the image's manifest row, and the manifest column each comes from.
_FROM_MANIFEST = {"image_path": "path", "class": "class", "modality": "modality", "split": "split",
                  "source": "source", "group": "group", "pair_key": "pair_key", "frame_w": "width", "frame_h": "height"}
_BOX_COLUMNS = ["tile_index", "box_x", "box_y", "box_w", "box_h"]


def _tile_one(args) -> list[tuple] | str:
    """``(tile file name, tile index, box)`` of each tile of one manifest image, written to
    ``tiles_dir/<modality>/<class>/``, or the reason the image gives no tile."""
    index, path, modality, cls, roi, tiles_dir, made = args
    try:
        image = read_rgb8(path).rgb
    except ImageError as exc:
        raise ImageError(f"{path}: {exc} (has it changed since the ingest stage? rerun ingest)") from exc
    try:
        boxes, tiles, reason = image_tiles(image, modality, roi)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    if reason:
        return reason
    folder = tiles_dir / modality / cls
    if folder not in made:  # one mkdir per folder, not per image (a race only repeats a harmless mkdir)
        folder.mkdir(parents=True, exist_ok=True)
        made.add(folder)
    out = []
    stem = Path(path).stem
    for k, (box, tile) in enumerate(zip(boxes, tiles)):
        name = f"{index:06d}_{stem}_{k}.png"
        write_png(folder / name, tile)
        out.append((f"{modality}/{cls}/{name}", k, box))
    return out


def cut_dataset_tiles(manifest: pd.DataFrame, roi: dict, tiles_dir: Path, workers: int = 2,
                      progress: bool = True, skipped: list[dict] | None = None) -> pd.DataFrame:
    """Cut all manifest images into ``tiles_dir``; return the tile table (``tile_path`` relative to it).

    Images that give no tile are appended to ``skipped`` as ``{"path", "reason"}``. The manifest
    is read lazily and at most a few images per worker are in flight, so memory holds the tile
    table (metadata) only, not the pixels of more than a handful of images.
    """
    tiles_dir, made = Path(tiles_dir), set()
    jobs = ((i, path, modality, cls, roi, tiles_dir, made) for i, (path, modality, cls) in
            enumerate(zip(manifest["path"], manifest["modality"], manifest["class"])))
    tile_paths: list[str] = []
    positions: list[int] = []  # the manifest row (by position) of each tile
    boxes: dict[str, list[int]] = {name: [] for name in _BOX_COLUMNS}
    # our workers are the parallelism: OpenCV's own thread pool on top of them only adds contention
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if workers > 1 else opencv_threads)
    try:
        results = stream_map(_tile_one, jobs, workers, len(manifest), "roi", progress)
        for position, tiles in enumerate(results):  # results come in manifest order
            if isinstance(tiles, str):
                if skipped is not None:
                    skipped.append({"path": manifest["path"].iat[position], "reason": tiles})
                continue
            for tile_path, k, box in tiles:
                tile_paths.append(tile_path)
                positions.append(position)
                for name, value in zip(_BOX_COLUMNS, (k, box.x, box.y, box.w, box.h)):
                    boxes[name].append(value)
    finally:
        cv2.setNumThreads(opencv_threads)
    rows = manifest.iloc[positions].reset_index(drop=True)  # one manifest row per tile, text copied once
    table = {"tile_path": tile_paths, **{column: rows[name] for column, name in _FROM_MANIFEST.items()}, **boxes}
    return pd.DataFrame(table, columns=TILE_COLUMNS)


def tile_preview(tiles: pd.DataFrame, tiles_dir: Path, per_class: int = 4, side: int = 96) -> np.ndarray:
    """A contact sheet for a person to look at: one row per class, ``per_class`` visual tiles then
    as many tactile tiles (aligned views side by side when the data has them), class name on the left."""
    rows = []
    for cls in sorted(tiles["class"].unique()):
        groups = []
        for modality in ("visual", "tactile"):
            chosen = tiles[(tiles["class"] == cls) & (tiles["modality"] == modality)].sort_values(["pair_key", "tile_index"])
            groups.append([read_rgb8(tiles_dir / path).rgb for path in chosen["tile_path"].head(per_class)])
        rows.append((cls, groups))
    return labelled_sheet(rows, ["visual", "tactile"], per_class, side)


def run_roi(manifest_path: str | Path, roi: dict, out_dir: str | Path, workers: int = 2) -> dict:
    """Stage entry: write ``tiles/`` and ``tiles.parquet`` (+ summary.json) into ``out_dir``."""
    manifest = read_table(manifest_path, MANIFEST_NEEDS, "the ingest stage's manifest")
    started = time.perf_counter()
    skipped: list[dict] = []
    with atomic_output_dir(out_dir) as tmp:
        tiles = cut_dataset_tiles(manifest, roi, tmp / "tiles", workers, skipped=skipped)
        if tiles.empty:
            reasons = sorted({s["reason"] for s in skipped})[:3]
            raise ValueError(f"{manifest_path}: no tiles cut from its {len(manifest)} images"
                             + (f" ({'; '.join(reasons)})" if reasons else ""))
        tiles.to_parquet(tmp / "tiles.parquet", index=False)
        write_png(tmp / "preview.png", tile_preview(tiles, tmp / "tiles"))
        seconds = time.perf_counter() - started
        summary = {
            "images": len(manifest), "tiles": len(tiles), "tile_size": roi["size"],
            "tiles_per_modality": tiles["modality"].value_counts().to_dict(),
            "seconds": round(seconds, 3),
            "images_per_second": round(len(manifest) / seconds, 1) if seconds > 0 else None,
            "skipped": skipped,
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"roi: {summary['images']} images -> {summary['tiles']} tiles of {roi['size']} px "
          f"({summary['images_per_second']} images/s)")
    for item in skipped:
        print(f"  warning: no tile from {item['path']}: {item['reason']}")
    return summary

