"""Pairing stage: assign splits by group and build the V2T and T2V pair tables.

Splits are decided per *group* (``group`` in tiles.parquet: the instance, session or source an
image came from, merged across exact and near-duplicates by ingest), never per image or tile, so
no group appears in two splits; this is checked after splitting and a violation is a bug
(RuntimeError). A split fixed by the dataset (ViTac ``_test`` folders) is kept; a group the
dataset itself puts in two splits is reported with counts. Otherwise ``pairing.test_fraction``
and ``pairing.val_fraction`` of each class's groups are held out, drawn with ``pairing.seed``.
A class and modality with fewer than ``pairing.min_test_images`` test images is warned about or
refused (``pairing.below_minimum``).

Pairs (``pair_kind``): tiles of images sharing a pair key are pairs at any resolution: ``pixel``
when the two frames have the same size and the tiles the same tile index and box (``aligned``),
``name`` otherwise (tiles matched by tile index when both images have several, else the first).
Every other target tile gets an input drawn at random from the same class and split (``class``),
as the authors did for ViTac. When one modality is missing altogether, the pair tables are empty
and the summary says why; the splits are written all the same.

The summary also says what kind of data the training split is (``data_kind``): whether every training pair
of both directions is a class pair, and if so the training photos' layout gap (:mod:`vtgen.core.layout`: texture
or scene), which ``translation.recipe: auto`` reads (:func:`vtgen.io.params.recipe_choice`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from PIL import Image

from vtgen.core.domain import DIRECTIONS
from vtgen.core.layout import layout_gap
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.io.tables import PAIR_COLUMNS, PAIR_KINDS, SPLIT_COLUMNS

SPLITS = ("train", "val", "test")
LAYOUT_PHOTOS_PER_CLASS = 50  # training photo tiles per class the layout gap is measured on (the first by path)
TILE_NEEDS = ["tile_path", "image_path", "class", "modality", "split", "source", "group", "pair_key", "tile_index",
              "box_x", "box_y", "box_w", "box_h", "frame_w", "frame_h"]


def assign_splits(tiles: pd.DataFrame, val_fraction: float, test_fraction: float, seed: int) -> tuple[pd.Series, list[str]]:
    """Split label per tile, decided per (class, group). Returns (labels aligned to ``tiles``, warnings).

    Tiles the dataset puts in its test (or val) split stay there, and a class with a fixed test
    split gets only a validation split carved from its other groups. Groups are sorted by the
    modalities they hold (visual only, tactile only, both) and each kind of a class is split on
    its own, so every split gets groups of every kind the class has.
    """
    rng = np.random.default_rng(seed)
    warnings: list[str] = []
    decided: dict[tuple[str, str], str] = {}
    for cls, part in tiles.groupby("class", sort=True):
        fixed = part["split"].isin(["test", "val"])
        fixed_groups = set(part.loc[fixed, "group"])
        straddling = sorted(g for g, s in part.groupby("group")["split"] if s.nunique() > 1 and g in fixed_groups)
        if straddling:
            rows = part[part["group"].isin(straddling)]
            counts = ", ".join(f"{n} {s or 'unassigned'}" for s, n in rows["split"].value_counts().sort_index().items())
            warnings.append(f"class {cls}: {len(straddling)} group(s) ({', '.join(map(str, straddling[:3]))}"
                            f"{', ...' if len(straddling) > 3 else ''}) have images in several of the dataset's own "
                            f"splits ({counts} tiles); the dataset's split is kept, so these groups are shared across "
                            f"splits")
        has_fixed_test = (part["split"] == "test").any()
        free = part[~part["group"].isin(fixed_groups)]
        kinds = free.groupby("group")["modality"].agg(lambda m: "+".join(sorted(set(m))))
        for kind in sorted(set(kinds)):
            groups = sorted(kinds.index[kinds == kind])
            order = [groups[i] for i in rng.permutation(len(groups))]
            n = len(order)
            n_test = 0 if has_fixed_test else _share(n, test_fraction)
            n_val = _share(n - n_test, val_fraction)
            for i, group in enumerate(order):
                decided[(cls, group)] = "test" if i < n_test else "val" if i < n_test + n_val else "train"
            if n_val == 0 and val_fraction > 0:
                warnings.append(f"class {cls}, {kind} groups: {n} free group(s), too few to hold out a validation split")
            if n_test == 0 and test_fraction > 0 and not has_fixed_test:
                warnings.append(f"class {cls}, {kind} groups: {n} group(s), too few to hold out a test split")
    labels = [
        fixed if fixed in ("test", "val") else decided.get((cls, group), "train")
        for cls, group, fixed in zip(tiles["class"], tiles["group"], tiles["split"])
    ]
    return pd.Series(labels, index=tiles.index, name="split"), warnings


def _share(n: int, fraction: float) -> int:
    """round(n * fraction), at least 1 when the fraction is positive; 0 when fewer than 2 groups."""
    if fraction <= 0 or n < 2:
        return 0
    return max(1, int(round(n * fraction)))


def check_groups_within_one_split(tiles: pd.DataFrame, dataset_splits: pd.Series) -> None:
    """Raise RuntimeError (a bug in the splitting) when a group lies in two splits, unless the dataset
    itself put it there (``dataset_splits``: the split column as the dataset gave it)."""
    per_group = tiles.assign(fixed=dataset_splits.isin(["test", "val"])).groupby(["class", "group"])
    for (cls, group), part in per_group:
        if part["split"].nunique() > 1 and not part["fixed"].any():
            raise RuntimeError(f"bug: group {group} of class {cls} was put in several splits "
                               f"({', '.join(sorted(part['split'].unique()))}); please report it")


def small_test_splits(tiles: pd.DataFrame, minimum: int) -> list[str]:
    """One line per class and modality whose test split holds fewer than ``minimum`` images."""
    problems = []
    images = tiles.drop_duplicates("image_path")
    for (cls, modality), part in images.groupby(["class", "modality"], sort=True):
        n = int((part["split"] == "test").sum())
        if n < minimum:
            problems.append(f"{cls}/{modality}: {n} test image(s)")
    return problems


def _partner(target: dict, candidates: list[dict]) -> tuple[dict, str]:
    """The input tile paired with ``target`` among the tiles of images sharing its pair key."""
    for row in candidates:
        if (row["frame_w"], row["frame_h"], row["tile_index"], row["box_x"], row["box_y"], row["box_w"], row["box_h"]) == (
                target["frame_w"], target["frame_h"], target["tile_index"], target["box_x"], target["box_y"],
                target["box_w"], target["box_h"]):
            return row, "pixel"
    image = min(c["image_path"] for c in candidates)
    tiles = sorted((c for c in candidates if c["image_path"] == image), key=lambda c: c["tile_index"])
    if len(tiles) > 1 and target["n_tiles"] > 1:
        for row in tiles:
            if row["tile_index"] == target["tile_index"]:
                return row, "name"
    return tiles[0], "name"


def build_pairs(tiles: pd.DataFrame, direction: str, seed: int) -> tuple[pd.DataFrame, list[str]]:
    """Pair table for ``direction`` ('v2t' or 't2v'): one row per target tile that has a partner.

    ``tiles`` needs a resolved ``split`` column (train/val/test) and ``path`` (the tile file).
    """
    source_mod, target_mod = DIRECTIONS[direction]
    rng = np.random.default_rng([seed, 0 if direction == "v2t" else 1])
    tiles = tiles.assign(n_tiles=tiles.groupby("image_path")["tile_index"].transform("size"))
    inputs = tiles[tiles["modality"] == source_mod]
    targets = tiles[tiles["modality"] == target_mod]
    by_key: dict[tuple, list[dict]] = {}
    for row in inputs[inputs["pair_key"] != ""].to_dict("records"):
        by_key.setdefault((row["class"], row["split"], row["pair_key"]), []).append(row)
    rows, warnings = [], []
    for (split, cls), part in targets.groupby(["split", "class"], sort=True):
        pool = inputs[(inputs["split"] == split) & (inputs["class"] == cls)].to_dict("records")
        for target in part.to_dict("records"):
            keyed = by_key.get((cls, split, target["pair_key"])) if target["pair_key"] else None
            if keyed:
                source_row, kind = _partner(target, keyed)
            elif pool:
                source_row, kind = pool[rng.integers(len(pool))], "class"
            else:
                continue  # reported below as unpaired
            rows.append({
                "direction": direction, "split": split, "class": cls,
                "input_path": source_row["path"], "target_path": target["path"],
                "input_source": source_row["source"], "target_source": target["source"], "aligned": kind == "pixel",
                "pair_kind": kind,
            })
        if not pool:
            warnings.append(f"{direction}: class {cls}, split {split}: no {source_mod} tiles, "
                            f"{len(part)} {target_mod} tiles left unpaired")
    return pd.DataFrame(rows, columns=PAIR_COLUMNS), warnings


def promised_pairs(tiles: pd.DataFrame) -> int:
    """Pair keys (per class) that images of both modalities carry: the pairs the data promises."""
    keyed = tiles[tiles["pair_key"] != ""]
    return int((keyed.groupby(["class", "pair_key"])["modality"].nunique() == 2).sum())


def run_pairing(tiles_path: str | Path, pairing: dict, out_dir: str | Path) -> dict:
    """Stage entry: write splits.parquet, v2t.parquet, t2v.parquet and summary.json into ``out_dir``."""
    tiles_path = Path(tiles_path)
    tiles = read_table(tiles_path, TILE_NEEDS, "the roi stage's tiles.parquet")
    if tiles.empty:
        raise ValueError(f"{tiles_path}: no tiles to pair")
    tiles["path"] = [str(tiles_path.parent / "tiles" / p) for p in tiles["tile_path"]]
    dataset_splits = tiles["split"].copy()
    tiles["split"], warnings = assign_splits(tiles, pairing["val_fraction"], pairing["test_fraction"], pairing["seed"])
    check_groups_within_one_split(tiles, dataset_splits)
    minimum = pairing.get("min_test_images", 0)
    small = small_test_splits(tiles, minimum)
    if small:
        message = (f"{len(small)} class/modality test split(s) below pairing.min_test_images = {minimum}: "
                   f"{'; '.join(small)}; their test scores rest on too few images")
        if pairing.get("below_minimum", "warn") == "refuse":
            raise ValueError(f"{tiles_path}: {message} (pairing.below_minimum is 'refuse'; lower the minimum, "
                             f"raise pairing.test_fraction or add data)")
        warnings.append(message)
    modalities = sorted(set(tiles["modality"]))
    translation = len(modalities) == 2
    reason = "" if translation else (f"translation needs both modalities and the data has only {modalities[0]} images; "
                                     f"the pair tables are empty, the splits serve classification")
    summary = {
        "tiles_per_split": {f"{s}/{m}": int(n) for (s, m), n in tiles.groupby(["split", "modality"]).size().items()},
        "groups_per_split": {f"{c}/{s}": int(n) for (c, s), n in tiles.groupby(["class", "split"])["group"].nunique().items()},
        "test_images": {f"{c}/{m}": int(n) for (c, m), n in tiles[tiles["split"] == "test"].drop_duplicates("image_path")
                        .groupby(["class", "modality"]).size().items()},
        "translation": {"possible": translation, "reason": reason},
    }
    promised = promised_pairs(tiles)
    with atomic_output_dir(out_dir) as tmp:
        tiles[SPLIT_COLUMNS].to_parquet(tmp / "splits.parquet", index=False)
        for direction in DIRECTIONS:
            if translation:
                pairs, pair_warnings = build_pairs(tiles, direction, pairing["seed"])
                warnings.extend(pair_warnings)
            else:
                pairs = pd.DataFrame(columns=PAIR_COLUMNS).astype({"aligned": bool})
            pairs.to_parquet(tmp / f"{direction}.parquet", index=False)
            summary[direction] = {}
            for split in SPLITS:
                part = pairs[pairs["split"] == split]
                summary[direction][split] = {"pairs": len(part), "aligned": int(part["aligned"].sum()),
                                             **{kind: int((part["pair_kind"] == kind).sum()) for kind in PAIR_KINDS}}
            if translation and promised:
                keyed_targets = tiles[(tiles["modality"] == DIRECTIONS[direction][1]) & (tiles["pair_key"] != "")]
                used = int((pairs["pair_kind"] != "class").sum())
                unused = len(keyed_targets) - used
                if unused > 0:
                    warnings.append(f"{direction}: the data promises pairs ({promised} pair key(s) carried by both "
                                    f"modalities), but {unused} of {len(keyed_targets)} target tiles with a pair key "
                                    f"got a class pair (their partner is missing or in another split)")
        summary["promised_pair_keys"] = promised
        class_only = translation and all(summary[d]["train"]["pairs"] > 0
                                         and summary[d]["train"]["class"] == summary[d]["train"]["pairs"] for d in DIRECTIONS)
        # the photos' layout matters to class pairs only (translation.recipe auto): other data reads no image here
        summary["data_kind"] = {"class_pairs_only": class_only, "classes": int(tiles.loc[tiles["split"] == "train", "class"].nunique()),
                                **(photo_layout(tiles) if class_only else {"layout_gap": None, "layout_gap_per_class": {}})}
        summary["groups_in_several_splits"] = leaked_groups(tiles)
        summary["warnings"] = warnings
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    if not translation:
        print(f"pairing: {reason}")
    for direction in DIRECTIONS:
        counts = ", ".join(f"{s} {v['pairs']} ({v['pixel']} pixel, {v['name']} name, {v['class']} class)"
                           for s, v in summary[direction].items())
        print(f"pairing {direction}: {counts}")
    kind = summary["data_kind"]
    if kind["layout_gap"] is not None:
        print(f"pairing: training photos' layout gap {kind['layout_gap']:.3f} (median over classes; "
              f"class pairs only: {'yes' if kind['class_pairs_only'] else 'no'})")
    for warning in warnings:
        print(f"  warning: {warning}")
    return summary


def photo_layout(tiles: pd.DataFrame) -> dict:
    """The training photos' layout gap (:func:`vtgen.core.layout.layout_gap`): per class the median over its first
    ``LAYOUT_PHOTOS_PER_CLASS`` training photo tiles by path, and the median over classes (None without photos)."""
    photos = tiles[(tiles["modality"] == "visual") & (tiles["split"] == "train")].sort_values("tile_path")
    per_class = {}
    for name, part in photos.groupby("class"):
        gaps = []
        for path in part["path"].head(LAYOUT_PHOTOS_PER_CLASS):
            with Image.open(path) as image:
                gaps.append(layout_gap(image))
        per_class[str(name)] = round(float(np.median(gaps)), 4)
    median = round(float(np.median(list(per_class.values()))), 4) if per_class else None
    return {"layout_gap": median, "layout_gap_per_class": per_class}


def leaked_groups(tiles: pd.DataFrame) -> list[str]:
    """Groups whose tiles fall in more than one split (empty unless the dataset fixed such a split)."""
    per_group = tiles.groupby(["class", "group"])["split"].nunique()
    return [f"{c}/{g}" for (c, g), n in per_group.items() if n > 1]


leaked_sources = leaked_groups  # the earlier name
