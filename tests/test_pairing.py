import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vtgen.io.tables import PAIR_COLUMNS
from vtgen.stages.pairs import assign_splits, build_pairs, leaked_groups as leaked_sources


def make_tiles(spec, aligned=True, tiles_per_image=2, fixed=None):
    """Tile table: spec = {class: n_sources}; aligned views share pair_key; fixed = {(class, source): split}."""
    rows = []
    for cls, n in spec.items():
        for i in range(n):
            for modality in ("visual", "tactile"):
                source = f"{cls}/{i}" if aligned else f"{cls}/{modality[0]}{i}"
                for k in range(tiles_per_image):
                    rows.append({
                        "path": f"{modality}/{cls}/{i}_{k}.png", "image_path": f"{modality}/{cls}/{i}.png",
                        "class": cls, "modality": modality,
                        "split": (fixed or {}).get((cls, source), ""), "source": source, "group": source,
                        "pair_key": source if aligned else "", "tile_index": k,
                        "box_x": 32 * k, "box_y": 0, "box_w": 32, "box_h": 32, "frame_w": 64, "frame_h": 32,
                    })
    return pd.DataFrame(rows)


@settings(max_examples=40, deadline=None)
@given(spec=st.dictionaries(st.sampled_from(list("abcdef")), st.integers(1, 12), min_size=1, max_size=4),
       aligned=st.booleans(), val=st.floats(0, 0.5), test=st.floats(0, 0.5), seed=st.integers(0, 2**16))
@pytest.mark.slow
def test_no_source_is_in_two_splits(spec, aligned, val, test, seed):
    tiles = make_tiles(spec, aligned)
    tiles["split"], _ = assign_splits(tiles, val, test, seed)
    assert leaked_sources(tiles) == []
    assert set(tiles["split"]) <= {"train", "val", "test"}
    # every class keeps training data
    assert (tiles.groupby("class")["split"].apply(lambda s: (s == "train").any())).all()
    for direction in ("v2t", "t2v"):
        pairs, _ = build_pairs(tiles, direction, seed)
        split_of = dict(zip(tiles["path"], tiles["split"]))
        class_of = dict(zip(tiles["path"], tiles["class"]))
        assert (pairs["input_path"].map(split_of) == pairs["split"]).all()
        assert (pairs["target_path"].map(split_of) == pairs["split"]).all()
        assert (pairs["input_path"].map(class_of) == pairs["target_path"].map(class_of)).all()
        assert pairs["aligned"].all() == aligned or pairs.empty


def test_fractions_are_respected_per_class():
    tiles = make_tiles({"a": 20, "b": 10})
    tiles["split"], warnings = assign_splits(tiles, 0.1, 0.2, seed=3)
    per_source = tiles.drop_duplicates(["class", "source"]).groupby(["class", "split"]).size().to_dict()
    assert per_source == {("a", "test"): 4, ("a", "val"): 2, ("a", "train"): 14,
                          ("b", "test"): 2, ("b", "val"): 1, ("b", "train"): 7}
    assert warnings == []


def test_split_depends_on_seed_only():
    tiles = make_tiles({"a": 20})
    first, _ = assign_splits(tiles, 0.1, 0.2, seed=1)
    again, _ = assign_splits(tiles.sample(frac=1, random_state=0).sort_index(), 0.1, 0.2, seed=1)
    other, _ = assign_splits(tiles, 0.1, 0.2, seed=2)
    assert first.equals(again)
    assert not first.equals(other)


def test_aligned_pairs_match_view_and_box():
    tiles = make_tiles({"a": 6}, aligned=True)
    tiles["split"], _ = assign_splits(tiles, 0.0, 0.0, seed=0)
    pairs, _ = build_pairs(tiles, "v2t", seed=0)
    assert len(pairs) == 12 and pairs["aligned"].all()
    # the input is the visual tile of the same source and tile index
    assert (pairs["input_path"].str.replace("visual/", "") == pairs["target_path"].str.replace("tactile/", "")).all()


def test_unaligned_pairs_draw_inputs_from_same_class_and_split():
    tiles = make_tiles({"a": 8, "b": 8}, aligned=False)
    tiles["split"], _ = assign_splits(tiles, 0.0, 0.25, seed=0)
    pairs, _ = build_pairs(tiles, "t2v", seed=0)
    assert not pairs["aligned"].any()
    assert len(pairs) == (tiles["modality"] == "visual").sum()  # one pair per target tile
    assert pairs["input_path"].str.startswith("tactile/").all()


def test_fixed_test_split_is_kept_and_shared_sources_are_reported():
    # ViTac-like: tactile frames are separate sources; all visual tiles come from one photo in train and test
    rows = []
    for i, split in enumerate(["train"] * 6 + ["test"] * 2):
        rows.append({"path": f"t/{i}.jpg", "image_path": f"t/{i}.jpg", "class": "11", "modality": "tactile",
                     "split": split, "source": f"frame{i}", "group": f"frame{i}", "pair_key": "", "tile_index": 0,
                     "box_x": 0, "box_y": 0, "box_w": 8, "box_h": 8, "frame_w": 8, "frame_h": 8})
        rows.append({"path": f"v/{i}.jpg", "image_path": f"v/{i}.jpg", "class": "11", "modality": "visual",
                     "split": split, "source": "IMG_2460", "group": "IMG_2460", "pair_key": "", "tile_index": 0,
                     "box_x": 0, "box_y": 0, "box_w": 8, "box_h": 8, "frame_w": 8, "frame_h": 8})
    tiles = pd.DataFrame(rows)
    tiles["split"], warnings = assign_splits(tiles, 0.2, 0.2, seed=0)
    tactile = tiles[tiles["modality"] == "tactile"]
    assert list(tactile["split"][-2:]) == ["test", "test"]
    assert "test" not in set(tactile["split"][:6]) and "val" in set(tactile["split"][:6])
    assert leaked_sources(tiles) == ["11/IMG_2460"]
    assert any("IMG_2460" in w and "shared across" in w and "6 train" in w and "2 test" in w for w in warnings)


@pytest.mark.parametrize("direction", ["v2t", "t2v"])
def test_missing_input_modality_in_a_split_is_reported(direction):
    tiles = make_tiles({"a": 4}, aligned=False)
    tiles["split"] = "train"
    drop = "visual" if direction == "v2t" else "tactile"
    tiles.loc[(tiles["modality"] == drop) & (tiles["source"].str.endswith("0")), "split"] = "test"
    tiles.loc[(tiles["modality"] != drop) & (tiles["source"].str.endswith("0")), "split"] = "val"
    pairs, warnings = build_pairs(tiles, direction, seed=0)
    assert "val" not in set(pairs["split"])
    assert any("split val" in w and "left unpaired" in w for w in warnings)


# --- pairs at any resolution, one-modality data, test-size check, leak check ----------------------

import json

import numpy as np

from conftest import write_image
from vtgen.stages.ingest import ingest_dataset
from vtgen.stages.pairs import check_groups_within_one_split, run_pairing


def tiles_of(manifest: pd.DataFrame) -> pd.DataFrame:
    """One full-frame tile per manifest image, as the roi stage would cut with a full-frame box."""
    return manifest.assign(image_path=manifest["path"], tile_path=manifest["path"], tile_index=0, box_x=0, box_y=0,
                           box_w=manifest["width"], box_h=manifest["height"], frame_w=manifest["width"],
                           frame_h=manifest["height"])


def write_tiles(tmp_path, tiles: pd.DataFrame):
    path = tmp_path / "roi" / "tiles.parquet"
    path.parent.mkdir(parents=True, exist_ok=True)
    if "tile_path" not in tiles:
        tiles = tiles.assign(tile_path=tiles["path"])
    tiles.drop(columns=["path"]).to_parquet(path, index=False)
    return path


def test_name_pairs_at_two_resolutions_stay_pairs(tmp_path):
    rng = np.random.default_rng(0)
    root = tmp_path / "raw"
    for cls in ("a", "b"):
        for i in range(10):
            write_image(root / cls / "touch" / f"m{i}.png", rng.integers(0, 256, (60, 80), dtype=np.uint8))
            write_image(root / cls / "camera" / f"m{i}.png", rng.integers(0, 256, (30, 30, 3), dtype=np.uint8))
    manifest, _, summary = ingest_dataset(root, {"source": "pattern", "pattern": "{class}/{modality}/{pair}.png"},
                                          progress=False)
    assert summary["groups_per_class"] == {"a": 10, "b": 10}  # the pair key groups both modalities
    tiles = tiles_of(manifest)
    tiles["split"], _ = assign_splits(tiles, 0.1, 0.3, seed=0)
    for direction in ("v2t", "t2v"):
        pairs, _ = build_pairs(tiles, direction, seed=0)
        assert len(pairs) == 20 and (pairs["pair_kind"] == "name").all() and not pairs["aligned"].any()
        stem = lambda s: s.str.rsplit("/", n=1).str[-1]  # noqa: E731
        assert (stem(pairs["input_path"]) == stem(pairs["target_path"])).all()
    # the same pair key with the same frame size and box is a pixel pair
    same = tiles.assign(frame_w=64, frame_h=64, box_w=64, box_h=64)
    pairs, _ = build_pairs(same, "v2t", seed=0)
    assert (pairs["pair_kind"] == "pixel").all() and pairs["aligned"].all()


def test_name_pairs_match_tiles_by_index_when_both_have_several():
    tiles = make_tiles({"a": 3}, aligned=True, tiles_per_image=3)
    tiles.loc[tiles["modality"] == "tactile", "frame_w"] = 999  # different frame: not pixel-aligned
    tiles["split"], _ = assign_splits(tiles, 0.0, 0.0, seed=0)
    pairs, _ = build_pairs(tiles, "v2t", seed=0)
    assert (pairs["pair_kind"] == "name").all()
    index = lambda s: s.str.extract(r"_(\d)\.png$")[0]  # noqa: E731
    assert (index(pairs["input_path"]) == index(pairs["target_path"])).all()
    one = tiles[~((tiles["modality"] == "visual") & (tiles["tile_index"] > 0))]  # the input has one tile only
    pairs, _ = build_pairs(one, "v2t", seed=0)
    assert (pairs["pair_kind"] == "name").all() and (index(pairs["input_path"]) == "0").all()


def test_a_group_in_two_splits_is_a_bug():
    tiles = make_tiles({"a": 4})
    tiles["split"] = "train"
    check_groups_within_one_split(tiles, tiles["split"].map(lambda s: ""))
    tiles.loc[tiles.index[0], "split"] = "test"
    with pytest.raises(RuntimeError, match="bug: group a/0 of class a was put in several splits"):
        check_groups_within_one_split(tiles, pd.Series("", index=tiles.index))


def run_on(tmp_path, tiles, **pairing):
    settings = {"val_fraction": 0.1, "test_fraction": 0.2, "seed": 0, "min_test_images": 5, "below_minimum": "warn"}
    path = write_tiles(tmp_path, tiles)
    summary = run_pairing(path, {**settings, **pairing}, tmp_path / "pairs")
    return summary, {d: pd.read_parquet(tmp_path / "pairs" / f"{d}.parquet") for d in ("v2t", "t2v")}


def test_tactile_only_data_gets_splits_and_empty_pair_tables(tmp_path):
    rng = np.random.default_rng(1)
    root = tmp_path / "raw"
    for cls in ("a", "b"):
        for i in range(10):
            write_image(root / cls / f"{i}.png", rng.integers(0, 256, (24, 24), dtype=np.uint8))
    manifest, _, summary = ingest_dataset(root, {"source": "pattern", "pattern": "{class}/{name}.png",
                                                 "modality": "tactile"}, progress=False)
    assert not summary["translation"]["possible"]
    summary, pairs = run_on(tmp_path, tiles_of(manifest).assign(tile_path=lambda t: t["path"].str.split("raw/").str[1]),
                            min_test_images=1)
    assert not summary["translation"]["possible"] and "only tactile" in summary["translation"]["reason"]
    for table in pairs.values():
        assert table.empty and list(table.columns) == list(PAIR_COLUMNS)
    splits = pd.read_parquet(tmp_path / "pairs" / "splits.parquet")
    assert len(splits) == 20 and set(splits["split"]) == {"train", "val", "test"}
    assert json.loads((tmp_path / "pairs" / "summary.json").read_text())["v2t"]["test"]["pairs"] == 0


def test_small_test_splits_are_warned_about_or_refused(tmp_path):
    tiles = make_tiles({"a": 10, "b": 30}, tiles_per_image=1)
    summary, _ = run_on(tmp_path, tiles, test_fraction=0.2, min_test_images=5)
    small = [w for w in summary["warnings"] if "min_test_images" in w]
    assert len(small) == 1 and "a/tactile: 2 test image(s)" in small[0] and "a/visual: 2" in small[0]
    assert "b/" not in small[0]
    with pytest.raises(ValueError, match=r"below pairing.min_test_images = 5: a/tactile: 2 test image\(s\)"):
        run_on(tmp_path, tiles, test_fraction=0.2, min_test_images=5, below_minimum="refuse")
    summary, _ = run_on(tmp_path, tiles, test_fraction=0.2, min_test_images=2, below_minimum="refuse")
    assert not any("min_test_images" in w for w in summary["warnings"])


def test_summary_counts_pair_kinds_and_unused_promised_pairs(tmp_path):
    tiles = make_tiles({"a": 10}, tiles_per_image=1)
    # one view's visual image is in another group: its pair ends up a class pair unless the split agrees
    summary, pairs = run_on(tmp_path, tiles, min_test_images=0)
    assert summary["promised_pair_keys"] == 10
    for direction in ("v2t", "t2v"):
        counts = summary[direction]
        assert sum(v["pixel"] for v in counts.values()) == 10 and sum(v["class"] for v in counts.values()) == 0
    broken = tiles.copy()
    broken.loc[(broken["modality"] == "visual") & (broken["source"] == "a/0"), "pair_key"] = "elsewhere"
    summary, _ = run_on(tmp_path, broken, min_test_images=0)
    assert summary["promised_pair_keys"] == 9
    assert any("promises pairs" in w and "1 of 10" in w for w in summary["warnings"])


@pytest.mark.parametrize("photo, kind", [("stripes", "texture"), ("disc", "scene")])
def test_the_summary_says_what_kind_of_data_trains(tmp_path, photo, kind):
    """data_kind (translation.recipe auto reads it): class pairs only, the training classes, and the training photos'
    median layout gap, measured on the tiles' pixels: low for a stripe texture, high for a disc on a ground."""
    rng = np.random.default_rng(0)
    tiles = make_tiles({"a": 10, "b": 10}, aligned=False, tiles_per_image=1)
    yy, xx = np.mgrid[:32, :32]
    for path in tiles["path"]:
        if photo == "stripes":
            image = (((xx + rng.integers(0, 4)) // 2) % 2 * 200 + rng.integers(0, 30, (32, 32))).astype(np.uint8)
        else:
            image = np.where((yy - 16) ** 2 + (xx - 12 - rng.integers(0, 8)) ** 2 < 100, 220, 30).astype(np.uint8)
        write_image(tmp_path / "roi" / "tiles" / path, image)
    summary, pairs = run_on(tmp_path, tiles, min_test_images=0)
    found = summary["data_kind"]
    assert found["class_pairs_only"] and found["classes"] == 2 and set(found["layout_gap_per_class"]) == {"a", "b"}
    assert (found["layout_gap"] < 0.1) if kind == "texture" else (found["layout_gap"] > 0.5)
    # aligned data trains pix2pix: no photo is read, no gap is given
    aligned, _ = run_on(tmp_path, make_tiles({"a": 10, "b": 10}, tiles_per_image=1), min_test_images=0)
    assert aligned["data_kind"] == {"class_pairs_only": False, "classes": 2, "layout_gap": None, "layout_gap_per_class": {}}
