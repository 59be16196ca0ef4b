import numpy as np
import pandas as pd
import pytest

from conftest import random_rgb, write_image
from vtgen.io.images import atomic_output_dir, read_rgb8
from vtgen.stages.ingest import ingest_dataset
from vtgen.core.roi import Box
from vtgen.stages.roi import crop_boxes, cut_dataset_tiles, run_roi, tactile_region

ROI = {"size": 16, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 1.0}


def test_crop_boxes_are_inside_the_region_in_frame_coordinates():
    region = Box(10, 20, 100, 60)
    (centre,) = crop_boxes(region, "centre", 0.5)
    assert centre == Box(10 + 35, 20 + 15, 30, 30)
    tiles = crop_boxes(region, "tiles", 0.5)
    assert len(tiles) == 3 * 2 and all(b.w == b.h == 30 for b in tiles)
    assert all(region.x <= b.x and b.x + b.w <= region.x + region.w and region.y <= b.y and b.y + b.h <= region.y + region.h
               for b in tiles)


def test_tactile_region_fixed_box_must_fit():
    frame = np.zeros((40, 50, 3), np.uint8)
    assert tactile_region(frame, "full") == Box(0, 0, 50, 40)
    assert tactile_region(frame, [5, 5, 20, 20]) == Box(5, 5, 20, 20)
    with pytest.raises(ValueError, match=r"does not fit a 50x40 frame"):
        tactile_region(frame, [40, 0, 20, 20])


def make_dataset(root, n=3):
    rng = np.random.default_rng(0)
    for i in range(n):
        for modality in ("visual", "tactile"):
            write_image(root / "c" / modality / f"s{i}.png", random_rgb(rng, 48))
    return ingest_dataset(root, "generic", progress=False)[0]


def test_tiles_record_source_and_box_and_match_the_crop(tmp_path):
    manifest = make_dataset(tmp_path / "raw")
    tiles = cut_dataset_tiles(manifest, {**ROI, "visual_crop": "tiles", "crop_fraction": 0.5}, tmp_path / "tiles", progress=False)
    assert len(tiles) == len(manifest) * 4
    assert set(tiles["image_path"]) == set(manifest["path"])
    row = tiles.iloc[5]
    image = read_rgb8(row["image_path"]).rgb
    crop = image[row["box_y"]:row["box_y"] + row["box_h"], row["box_x"]:row["box_x"] + row["box_w"]]
    tile = read_rgb8(tmp_path / "tiles" / row["tile_path"]).rgb
    assert tile.shape == (16, 16, 3)
    assert abs(float(tile.mean()) - float(crop.mean())) < 2.0  # INTER_AREA averages the crop
    # aligned views keep equal boxes in both modalities
    per_view = tiles.groupby(["pair_key", "tile_index"])[["box_x", "box_y", "box_w", "box_h"]].nunique()
    assert (per_view == 1).all().all()


def test_bad_fixed_box_names_the_file(tmp_path):
    manifest = make_dataset(tmp_path / "raw", n=1)
    with pytest.raises(ValueError, match=r"tactile/s0\.png: roi\.tactile_box \[0, 0, 100, 100\] does not fit"):
        cut_dataset_tiles(manifest, {**ROI, "tactile_box": [0, 0, 100, 100]}, tmp_path / "tiles", progress=False)


def test_failed_stage_keeps_previous_output_and_leaves_no_temporary(tmp_path):
    manifest = make_dataset(tmp_path / "raw")
    manifest.to_parquet(tmp_path / "manifest.parquet")
    run_roi(tmp_path / "manifest.parquet", ROI, tmp_path / "roi")
    before = pd.read_parquet(tmp_path / "roi" / "tiles.parquet")
    with pytest.raises(ValueError):
        run_roi(tmp_path / "manifest.parquet", {**ROI, "tactile_box": [0, 0, 999, 999]}, tmp_path / "roi")
    pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "roi" / "tiles.parquet"), before)
    preview = read_rgb8(tmp_path / "roi" / "preview.png").rgb
    assert preview.shape == (24 + 96, 120 + 8 * 96, 3)  # header, one class row, 4 visual + 4 tactile slots
    assert sorted(p.name for p in tmp_path.iterdir()) == ["manifest.parquet", "raw", "roi"]


def test_atomic_output_dir_replaces_whole_folder(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(out) as tmp:
        (tmp / "a.txt").write_text("1")
    with atomic_output_dir(out) as tmp:
        (tmp / "b.txt").write_text("2")
    assert sorted(p.name for p in out.iterdir()) == ["b.txt"]


def test_vitac_tactile_tiles_with_marker_removal(vitac_root, tmp_path):
    manifest = ingest_dataset(vitac_root, "vitac", progress=False)[0]
    tactile = manifest[manifest["modality"] == "tactile"].head(4)
    plain = cut_dataset_tiles(tactile, {**ROI, "size": 64}, tmp_path / "plain", progress=False)
    clean = cut_dataset_tiles(tactile, {**ROI, "size": 64, "remove_markers": True, "tactile_box": "auto"},
                              tmp_path / "clean", progress=False)
    assert (clean[["box_w", "box_h"]] == 256).all().all()  # ViTac tiles are all contact
    dark = lambda root, p: (read_rgb8(root / p).rgb.mean(axis=2) < 60).mean()
    before = np.mean([dark(tmp_path / "plain", p) for p in plain["tile_path"]])
    after = np.mean([dark(tmp_path / "clean", p) for p in clean["tile_path"]])
    assert before > 0.02 and after < before / 4  # dark marker dots are gone
