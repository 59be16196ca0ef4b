"""class_gan.views: more crops of each training frame (the ROI rule's side and cleaning, at random places in
the frame's region), cut once before training and added as class pairs and inputs of the frame's class."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from conftest import tiny_params, write_image
from vtgen.core.roi import Box, image_roi, random_crops
from vtgen.stages.ingest import run_ingest
from vtgen.stages.pairs import run_pairing
from vtgen.stages.roi import run_roi
from vtgen.stages.train import (frame_views, load_pair_data, objective_settings, run_train, with_frame_views)

ROI = {"size": 16, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 0.5}


def coded_image(width: int, height: int) -> np.ndarray:
    """Each pixel tells where it is: red = x, green = y (both < 256), blue 0."""
    y, x = np.mgrid[0:height, 0:width]
    return np.stack([x, y, np.zeros_like(x)], axis=-1).astype(np.uint8)


def test_random_crops_are_the_roi_rules_side_at_random_places_inside_the_region():
    image = coded_image(200, 120)
    roi = dict(ROI, size=60)  # crop side floor(0.5 * 120) = 60: tiles are the crops themselves, no resampling
    boxes, tiles = random_crops(image, "visual", roi, 12, np.random.default_rng(3))
    assert len(boxes) == len(tiles) == 12
    for box, tile in zip(boxes, tiles):
        assert box.w == box.h == 60 and box.fits(200, 120)
        np.testing.assert_array_equal(tile, image[box.y:box.y + 60, box.x:box.x + 60])
    assert len({(b.x, b.y) for b in boxes}) > 6  # places vary (61 x 141 possible)
    again, _ = random_crops(image, "visual", roi, 12, np.random.default_rng(3))
    assert again == boxes
    centre = image_roi(image, "visual", roi)
    assert centre.boxes == [Box(70, 30, 60, 60)]  # the ROI stage's own tile is the centred one
    assert random_crops(image, "visual", roi, 0, np.random.default_rng(3)) == ([], [])


def test_random_crops_of_a_tactile_frame_stay_inside_its_fixed_region():
    frame = coded_image(160, 120)
    roi = dict(ROI, tactile_box=[40, 20, 100, 80], size=40)
    boxes, tiles = random_crops(frame, "tactile", roi, 20, np.random.default_rng(0))
    for box, tile in zip(boxes, tiles):
        assert box.w == box.h == 40
        assert 40 <= box.x and box.x + 40 <= 140 and 20 <= box.y and box.y + 40 <= 100
        np.testing.assert_array_equal(tile, frame[box.y:box.y + 40, box.x:box.x + 40])


def class_paired_project(root, per_class=4, side=64):
    """Generic-layout frames of two classes whose photos and touches have different names (class pairs), run
    through the real ingest, roi and pairs stages. Class ``a``'s photos are dark in red (< 100), ``b``'s
    bright (> 150), so any crop tells which class's frame it came from."""
    rng = np.random.default_rng(0)
    for cls, (low, high) in {"a": (0, 100), "b": (150, 256)}.items():
        for i in range(per_class):
            photo = rng.integers(0, 256, (side, side + 16, 3), dtype=np.uint8)
            photo[..., 0] = rng.integers(low, high, (side, side + 16), dtype=np.uint8)
            write_image(root / "raw" / cls / "visual" / f"p{i}.png", photo)
            write_image(root / "raw" / cls / "tactile" / f"t{i}.png", rng.integers(0, 256, (side, side, 3), dtype=np.uint8))
    run_ingest(root / "raw", "generic", root / "ingest", workers=1)
    run_roi(root / "ingest" / "manifest.parquet", ROI, root / "roi", workers=1)
    run_pairing(root / "roi" / "tiles.parquet", {"val_fraction": 0.0, "test_fraction": 0.25, "seed": 0,
                                                  "min_test_images": 1, "below_minimum": "warn"}, root / "pairs")
    pairs = pd.read_parquet(root / "pairs" / "v2t.parquet")
    splits = pd.read_parquet(root / "pairs" / "splits.parquet")
    return pairs, splits


def test_views_add_crops_of_each_frame_as_pairs_and_inputs_of_its_class(tmp_path):
    pairs, splits = class_paired_project(tmp_path)
    assert set(pairs["pair_kind"]) == {"class"}
    data = load_pair_data(pairs, splits, "v2t", "all", 16)
    tiles_path = tmp_path / "roi" / "tiles.parquet"
    assert with_frame_views(data, pairs, splits, "v2t", "all", 1, tiles_path, ROI, 16, seed=0) is data
    more = with_frame_views(data, pairs, splits, "v2t", "all", 3, tiles_path, ROI, 16, seed=0)
    n, m = len(data.targets), len(data.pool_images)
    assert len(more.targets) == len(more.inputs) == len(more.classes) == 3 * n and len(more.pool_images) == 3 * m
    assert torch.equal(more.targets[:n], data.targets) and torch.equal(more.pool_images[:m], data.pool_images)
    assert more.classes[n:] == [c for c in data.classes for _ in range(2)]
    assert not more.fixed.any() and not more.aligned.any()
    for cls, index in more.input_pool.items():  # every input a class pair draws is a crop of a photo of its class
        red = more.pool_images[index][:, 0].float()
        assert len(index) == 3 * len(data.input_pool[cls])
        assert (red.amax(dim=(1, 2)) < 100).all() if cls == "a" else (red.amin(dim=(1, 2)) > 150).all()
    extra = more.pool_images[m:]
    assert not any(torch.equal(extra[k], data.pool_images[k // 2]) for k in range(len(extra)))  # not the centre tile again
    other_seed = with_frame_views(data, pairs, splits, "v2t", "all", 3, tiles_path, ROI, 16, seed=1)
    assert not torch.equal(other_seed.pool_images[m:], extra)


def test_a_tiles_crops_do_not_depend_on_the_other_tiles_asked_for(tmp_path):
    pairs, splits = class_paired_project(tmp_path)
    tiles = pd.read_parquet(tmp_path / "roi" / "tiles.parquet")
    tiles_dir = tmp_path / "roi" / "tiles"
    paths = list(splits[splits["split"] == "train"]["path"])
    forward = frame_views(paths, tiles, tiles_dir, ROI, 2, 16, seed=5)
    backward = frame_views(paths[::-1], tiles, tiles_dir, ROI, 2, 16, seed=5)
    assert forward.shape == (2 * len(paths), 3, 16, 16)
    assert torch.equal(forward.view(len(paths), 2, 3, 16, 16), backward.view(len(paths), 2, 3, 16, 16).flip(0))
    with pytest.raises(ValueError, match=r"elsewhere\.png: tile not in the roi stage's table"):
        frame_views(["data/roi/tiles/elsewhere.png"], tiles, tiles_dir, ROI, 2, 16, seed=5)


def test_views_one_adds_no_setting_and_more_views_are_a_setting_per_direction():
    translation = tiny_params()["translation"]
    settings = {"batch_size": 2, "iterations": 10}
    assert "views" not in objective_settings(settings, translation, "class_gan", "v2t")
    per_direction = dict(translation, class_gan=dict(translation["class_gan"], views={"v2t": 4, "t2v": 1}))
    assert objective_settings(settings, per_direction, "class_gan", "v2t")["views"] == 4
    assert "views" not in objective_settings(settings, per_direction, "class_gan", "t2v")


@pytest.mark.slow
def test_the_train_stage_trains_on_the_views_and_records_them(tmp_path, monkeypatch):
    class_paired_project(tmp_path)
    monkeypatch.chdir(tmp_path)
    params = tiny_params(roi=ROI)
    params["translation"]["class_gan"]["views"] = {"v2t": 3, "t2v": 1}
    params["translation"]["capacity"]["mode"] = "fixed"
    params["presets"]["fast"].update(size=16, iterations=4)
    summary = run_train(params, "v2t", "all", "pairs", "models/v2t/all", "checkpoints", progress=False,
                        tiles_path="roi/tiles.parquet")
    frames = summary["views"]["target_frames"]
    assert summary["views"] == {"per_frame": 3, "target_frames": frames, "targets": 3 * frames,
                                "inputs": 3 * frames}  # as many photos as touches here
    assert summary["settings"]["views"] == 3
    assert json.loads((tmp_path / "models/v2t/all/train.json").read_text())["views"]["targets"] == 3 * frames
    plain = run_train(params, "t2v", "all", "pairs", "models/t2v/all", "checkpoints", progress=False,
                      tiles_path="roi/tiles.parquet")
    assert plain["views"]["per_frame"] == 1 and "views" not in plain["settings"]
