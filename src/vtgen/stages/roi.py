"""ROI stage: cut every manifest image into square tiles at the model resolution.

Writes ``tiles/``, ``tiles.parquet``, ``regions.parquet``, ``summary.json`` and ``preview.png``
(visual and tactile tiles per class).

Each image goes through :func:`vtgen.core.roi.image_roi`, the per-image rule that
:func:`vtgen.core.roi.image_tiles` also exposes to other stages: a *region* is chosen first (for
tactile frames per ``roi.tactile_box``: ``auto`` finds a round sensor's disc, else a GelSight
contact rectangle; ``full`` frame; or a fixed ``[x, y, w, h]``; for visual images the whole
photo); inside it ``roi.visual_crop`` cuts one centred square (``centre``) or a grid of squares
(``tiles``) whose side is ``roi.crop_fraction`` of the region's shorter side; each crop is resized
to ``roi.size``. The same crop rule applies to both modalities, so aligned data (equal regions)
gives aligned tiles with equal boxes. ``roi.remove_markers`` paints marker dots out of tactile tiles.

``regions.parquet`` has one row per manifest image (:data:`REGION_COLUMNS`): the region's shape
(``disc``, ``rectangle``, ``frame``, ``fixed``; "" for a skipped image) and box, the disc fit when
one was tried (centre, radius, ``disc_support``: the confidence, ``disc_overlap``, ``disc_found``),
the fallback used (``note``) and ``channels`` (1 when the image is greyscale in content).
``summary.json`` counts the shapes per modality (``regions``) and gives ``channels`` per modality
(1 when every image of it is greyscale: the tiles then hold three equal channels).

An image too small for the centre crop (``crop_fraction`` of its shorter side is under one
pixel) gives no tile; it is listed with the reason under ``skipped`` in ``summary.json``.
Images are read, cut and written one per worker process at a time, in batches of 8, with at most
4 batches per worker in flight (:func:`vtgen.io.images.stream_map`); the manifest is read row by
row and each image's tiles are written before the worker reads its next image. Only the tile and
region tables are kept in memory, built column by column. JPEG files are decoded with OpenCV (the same pixels as
:func:`vtgen.io.images.read_rgb8`, checked in the tests; a greyscale JPEG stays one channel until
its tiles are cut), anything else with ``read_rgb8``; tiles are written as RGB PNG (zlib level 1).
"""

from __future__ import annotations

import dataclasses
import json
import time
from array import array
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from vtgen.io.timing import write_timing
from vtgen.io.images import atomic_output_dir, ImageError, labelled_sheet, read_for_roi, read_rgb8, stream_map, write_png
from vtgen.io.tables import read_table
from vtgen.core.roi import crop_boxes, image_roi, ImageROI, tactile_region  # noqa: F401 - crop_boxes, tactile_region: re-exported
from vtgen.io.tables import TILE_COLUMNS

MANIFEST_NEEDS = ["path", "class", "modality", "split", "source", "group", "pair_key", "width", "height"]


# The tile table's columns taken from the image's manifest row, and the manifest column each comes from.
_FROM_MANIFEST = {"image_path": "path", "class": "class", "modality": "modality", "split": "split",
                  "source": "source", "group": "group", "pair_key": "pair_key", "frame_w": "width", "frame_h": "height"}
_BOX_COLUMNS = ["tile_index", "box_x", "box_y", "box_w", "box_h"]


REGION_COLUMNS = ["image_path", "modality", "class", "shape", "region_x", "region_y", "region_w", "region_h",
                  "disc_found", "disc_cx", "disc_cy", "disc_radius", "disc_support", "disc_overlap", "note", "channels"]


def write_tile_png(path: Path, rgb: np.ndarray) -> None:
    """Write a (size, size, 3) uint8 RGB tile as an RGB PNG, zlib level 1 (as ``write_png``: the same
    pixels and size; OpenCV's encoder is faster)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    encoded.tofile(path)


def _is_grey(image: np.ndarray, tiles: list[np.ndarray]) -> bool:
    """Greyscale in content: a one-channel image, or tiles whose three channels are equal."""
    return image.ndim == 2 or all(
        np.array_equal(t[..., 0], t[..., 1]) and np.array_equal(t[..., 1], t[..., 2]) for t in tiles)


def _tile_one(args) -> tuple[ImageROI, int, list[str]]:
    """The ROI of one manifest image (without its tile pixels, which are written here), its channels
    (1: greyscale content) and the tile file names (relative to ``tiles_dir``) written to
    ``tiles_dir/<modality>/<class>/``."""
    index, path, modality, cls, roi, tiles_dir = args
    try:
        image = read_for_roi(path)
    except ImageError as exc:
        raise ImageError(f"{path}: {exc} (has it changed since the ingest stage? rerun ingest)") from exc
    try:
        result = image_roi(image, modality, roi)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    channels = 1 if _is_grey(image, result.tiles) else 3
    if result.reason:
        return result, channels, []
    folder = tiles_dir / modality / cls
    folder.mkdir(parents=True, exist_ok=True)  # a few microseconds; workers may race on it harmlessly
    names = []
    stem = Path(path).stem
    for k, tile in enumerate(result.tiles):
        name = f"{index:06d}_{stem}_{k}.png"
        write_tile_png(folder / name, tile)
        names.append(f"{modality}/{cls}/{name}")
    return dataclasses.replace(result, tiles=[]), channels, names


class _RegionRecorder:
    """The region table, column by column in compact arrays (metadata only, a few dozen bytes per image)."""

    def __init__(self) -> None:
        self.shape: list[str] = []
        self.note: list[str] = []
        self.ints = {name: array("i") for name in ("region_x", "region_y", "region_w", "region_h", "disc_found", "channels")}
        self.floats = {name: array("d") for name in ("disc_cx", "disc_cy", "disc_radius", "disc_support", "disc_overlap")}

    def add(self, result: ImageROI, channels: int) -> None:
        region, nan = result.region, float("nan")
        box = region.box if region is not None else None
        disc = region.disc if region is not None else None
        self.shape.append(region.shape if region is not None else "")
        self.note.append(result.reason or (region.note if region is not None else ""))
        for name, value in zip(("region_x", "region_y", "region_w", "region_h"), (box.x, box.y, box.w, box.h) if box else (-1,) * 4):
            self.ints[name].append(value)
        self.ints["disc_found"].append(-1 if disc is None else int(disc.found))
        self.ints["channels"].append(channels)
        values = (disc.cx, disc.cy, disc.radius, disc.support, disc.overlap) if disc is not None else (nan,) * 5
        for name, value in zip(self.floats, values):
            self.floats[name].append(value)

    def table(self, manifest: pd.DataFrame) -> pd.DataFrame:
        found = np.asarray(self.ints["disc_found"], np.int8)
        columns = {"image_path": manifest["path"].to_numpy(), "modality": manifest["modality"].to_numpy(),
                   "class": manifest["class"].to_numpy(), "shape": self.shape,
                   **{name: np.asarray(self.ints[name], np.int32) for name in ("region_x", "region_y", "region_w", "region_h")},
                   "disc_found": pd.array([None if f < 0 else bool(f) for f in found], dtype="boolean"),
                   **{name: np.asarray(values, np.float64) for name, values in self.floats.items()},
                   "note": self.note, "channels": np.asarray(self.ints["channels"], np.int8)}
        return pd.DataFrame(columns, columns=REGION_COLUMNS)


def cut_dataset_tiles(manifest: pd.DataFrame, roi: dict, tiles_dir: Path, workers: int = 2,
                      progress: bool = True, skipped: list[dict] | None = None,
                      regions: list[pd.DataFrame] | None = None) -> pd.DataFrame:
    """Cut all manifest images into ``tiles_dir``; return the tile table (``tile_path`` relative to it).

    Images that give no tile are appended to ``skipped`` as ``{"path", "reason"}``; the region
    table (:data:`REGION_COLUMNS`, one row per manifest image) is appended to ``regions`` when given.
    The manifest is read lazily and at most a few batches of images per worker are in flight, so memory
    holds the tables (metadata) only, not the pixels of more than a few dozen images.
    """
    tiles_dir = Path(tiles_dir)
    jobs = ((i, path, modality, cls, roi, tiles_dir) for i, (path, modality, cls) in
            enumerate(zip(manifest["path"], manifest["modality"], manifest["class"])))
    tile_paths: list[str] = []
    positions = array("i")  # the manifest row (by position) of each tile
    boxes = {name: array("i") for name in _BOX_COLUMNS}
    recorder = _RegionRecorder()
    # Worker processes, not threads: the disc search's many small numpy steps hold the GIL (on 480
    # vt60 frames 2 threads gave 1.3x one thread, 2 processes 1.9x: benchmarks/README.md).
    results = stream_map(_tile_one, jobs, workers, len(manifest), "roi", progress, processes=True)
    for position, (result, channels, names) in enumerate(results):  # results come in manifest order
        recorder.add(result, channels)
        if result.reason:
            if skipped is not None:
                skipped.append({"path": manifest["path"].iat[position], "reason": result.reason})
            continue
        for k, (tile_path, box) in enumerate(zip(names, result.boxes)):
            tile_paths.append(tile_path)
            positions.append(position)
            for name, value in zip(_BOX_COLUMNS, (k, box.x, box.y, box.w, box.h)):
                boxes[name].append(value)
    if regions is not None:
        regions.append(recorder.table(manifest))
    rows = manifest.iloc[np.asarray(positions, np.intp)].reset_index(drop=True)  # one manifest row per tile
    table = {"tile_path": tile_paths, **{column: rows[name] for column, name in _FROM_MANIFEST.items()},
             **{name: np.asarray(values, np.int64) for name, values in boxes.items()}}
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
    """Stage entry: write ``tiles/``, ``tiles.parquet``, ``regions.parquet``, ``summary.json`` and
    ``preview.png`` into ``out_dir`` (its seconds and images per second into ``timing.json``); return the summary
    with those times."""
    manifest = read_table(manifest_path, MANIFEST_NEEDS, "the ingest stage's manifest")
    started = time.perf_counter()
    skipped: list[dict] = []
    regions: list[pd.DataFrame] = []
    with atomic_output_dir(out_dir) as tmp:
        tiles = cut_dataset_tiles(manifest, roi, tmp / "tiles", workers, skipped=skipped, regions=regions)
        if tiles.empty:
            reasons = sorted({s["reason"] for s in skipped})[:3]
            raise ValueError(f"{manifest_path}: no tiles cut from its {len(manifest)} images"
                             + (f" ({'; '.join(reasons)})" if reasons else ""))
        tiles.to_parquet(tmp / "tiles.parquet", index=False)
        region_table = regions[0]
        region_table.to_parquet(tmp / "regions.parquet", index=False)
        write_png(tmp / "preview.png", tile_preview(tiles, tmp / "tiles"))
        seconds = time.perf_counter() - started
        cut = region_table[region_table["shape"] != ""]
        summary = {
            "images": len(manifest), "tiles": len(tiles), "tile_size": roi["size"],
            "tiles_per_modality": tiles["modality"].value_counts().to_dict(),
            "regions": {modality: group["shape"].value_counts().sort_index().to_dict()
                        for modality, group in cut.groupby("modality", sort=True)},
            "channels": {modality: int(group["channels"].max()) for modality, group in cut.groupby("modality", sort=True)},
            "skipped": skipped,
        }
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        times = {"seconds": round(seconds, 3),
                 "images_per_second": round(len(manifest) / seconds, 1) if seconds > 0 else None}
        # the cutting alone, apart from the command's wall time (its "seconds")
        write_timing(tmp, {"work_seconds": times["seconds"], "images_per_second": times["images_per_second"]})
    print(f"roi: {summary['images']} images -> {summary['tiles']} tiles of {roi['size']} px "
          f"({times['images_per_second']} images/s)")
    for item in skipped:
        print(f"  warning: no tile from {item['path']}: {item['reason']}")
    return {**summary, **times}

