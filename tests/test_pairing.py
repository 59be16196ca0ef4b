import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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
