"""Pairing stage: assign splits by source and build the V2T and T2V pair tables.

Splits are decided per *source* (the physical sample or GelSight frame an image came from),
never per tile, so no source appears in two splits. A split fixed by the dataset (ViTac
``_test`` folders) is kept; otherwise ``pairing.test_fraction`` and ``pairing.val_fraction`` of
each class's sources are held out, drawn with ``pairing.seed``.

Pairs: where a visual and a tactile tile share ``pair_key``, ``tile_index`` and box they are
one aligned view and form an aligned pair. Every other target tile gets an input drawn at
random from the same class and split, as the authors did for ViTac, where the modalities are
not aligned.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from vtgen.core.domain import DIRECTIONS
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS

SPLITS = ("train", "val", "test")
TILE_NEEDS = ["tile_path", "class", "modality", "split", "source", "pair_key", "tile_index",
              "box_x", "box_y", "box_w", "box_h"]
def assign_splits(tiles: pd.DataFrame, val_fraction: float, test_fraction: float, seed: int) -> tuple[pd.Series, list[str]]:
    """Split label per tile, decided per (class, source). Returns (labels aligned to ``tiles``, warnings).

    Tiles the dataset puts in its test split stay there, and a class with such a fixed test
    split gets only a validation split carved from its other sources. Sources are grouped by
    the modalities they hold (visual only, tactile only, both) and each group of a class is
    split on its own, so every split gets sources of every kind the class has.
    """
    rng = np.random.default_rng(seed)
    warnings: list[str] = []
    decided: dict[tuple[str, str], str] = {}
    for cls, group in tiles.groupby("class", sort=True):
        is_fixed_test = group["split"] == "test"
        fixed_test_sources = set(group.loc[is_fixed_test, "source"])
        for source in sorted(fixed_test_sources & set(group.loc[~is_fixed_test, "source"])):
            warnings.append(f"class {cls}: source {source} has images in the dataset's train and test folders; "
                            f"the dataset's split is kept, so this source is shared across splits")
        free = group[~group["source"].isin(fixed_test_sources)]
        kinds = free.groupby("source")["modality"].agg(lambda m: "+".join(sorted(set(m))))
        for kind in sorted(set(kinds)):
            sources = sorted(kinds.index[kinds == kind])
            order = [sources[i] for i in rng.permutation(len(sources))]
            n = len(order)
            n_test = 0 if is_fixed_test.any() else _share(n, test_fraction)
            n_val = _share(n - n_test, val_fraction)
            for i, source in enumerate(order):
                decided[(cls, source)] = "test" if i < n_test else "val" if i < n_test + n_val else "train"
            if n_val == 0 and val_fraction > 0:
                warnings.append(f"class {cls}, {kind} sources: {n} free source(s), too few to hold out a validation split")
            if n_test == 0 and test_fraction > 0 and not is_fixed_test.any():
                warnings.append(f"class {cls}, {kind} sources: {n} source(s), too few to hold out a test split")
    labels = [
        "test" if fixed == "test" else decided.get((cls, source), "train")
        for cls, source, fixed in zip(tiles["class"], tiles["source"], tiles["split"])
    ]
    return pd.Series(labels, index=tiles.index, name="split"), warnings


def _share(n: int, fraction: float) -> int:
    """round(n * fraction), at least 1 when the fraction is positive; 0 when fewer than 2 sources."""
    if fraction <= 0 or n < 2:
        return 0
    return max(1, int(round(n * fraction)))


def build_pairs(tiles: pd.DataFrame, direction: str, seed: int) -> tuple[pd.DataFrame, list[str]]:
    """Pair table for ``direction`` ('v2t' or 't2v'): one row per target tile that has a partner.

    ``tiles`` needs a resolved ``split`` column (train/val/test) and ``path`` (the tile file).
    """
    source_mod, target_mod = DIRECTIONS[direction]
    rng = np.random.default_rng([seed, 0 if direction == "v2t" else 1])
    keyed = tiles.assign(key=list(zip(tiles["class"], tiles["pair_key"], tiles["tile_index"], tiles["box_x"], tiles["box_y"],
                                      tiles["box_w"], tiles["box_h"])))
    inputs = keyed[keyed["modality"] == source_mod]
    targets = keyed[keyed["modality"] == target_mod]
    aligned_input = {k: row for k, row in zip(inputs["key"], inputs.to_dict("records")) if k[1] != ""}
    rows, warnings = [], []
    for (split, cls), group in targets.groupby(["split", "class"], sort=True):
        pool = inputs[(inputs["split"] == split) & (inputs["class"] == cls)].to_dict("records")
        for target in group.to_dict("records"):
            partner = aligned_input.get(target["key"]) if target["pair_key"] else None
            if partner is not None and partner["split"] == split:
                source_row, aligned = partner, True
            elif pool:
                source_row, aligned = pool[rng.integers(len(pool))], False
            else:
                continue  # reported below as unpaired
            rows.append({
                "direction": direction, "split": split, "class": cls,
                "input_path": source_row["path"], "target_path": target["path"],
                "input_source": source_row["source"], "target_source": target["source"], "aligned": aligned,
                "pair_kind": "pixel" if aligned else "class",
            })
        if not pool:
            warnings.append(f"{direction}: class {cls}, split {split}: no {source_mod} tiles, "
                            f"{len(group)} {target_mod} tiles left unpaired")
    return pd.DataFrame(rows, columns=PAIR_COLUMNS), warnings


def run_pairing(tiles_path: str | Path, pairing: dict, out_dir: str | Path) -> dict:
    """Stage entry: write splits.parquet, v2t.parquet, t2v.parquet and summary.json into ``out_dir``."""
    tiles_path = Path(tiles_path)
    tiles = read_table(tiles_path, TILE_NEEDS, "the roi stage's tiles.parquet")
    if tiles.empty:
        raise ValueError(f"{tiles_path}: no tiles to pair")
    tiles["path"] = [str(tiles_path.parent / "tiles" / p) for p in tiles["tile_path"]]
    tiles["split"], warnings = assign_splits(tiles, pairing["val_fraction"], pairing["test_fraction"], pairing["seed"])
    leaks = leaked_sources(tiles)
    summary = {"tiles_per_split": {f"{s}/{m}": int(n) for (s, m), n in tiles.groupby(["split", "modality"]).size().items()}}
    with atomic_output_dir(out_dir) as tmp:
        tiles[SPLIT_COLUMNS].to_parquet(tmp / "splits.parquet", index=False)
        for direction in DIRECTIONS:
            pairs, pair_warnings = build_pairs(tiles, direction, pairing["seed"])
            warnings.extend(pair_warnings)
            pairs.to_parquet(tmp / f"{direction}.parquet", index=False)
            summary[direction] = {
                f"{split}": {"pairs": int((pairs["split"] == split).sum()),
                             "aligned": int(pairs.loc[pairs["split"] == split, "aligned"].sum())}
                for split in SPLITS
            }
        summary["sources_in_several_splits"] = leaks
        summary["warnings"] = warnings
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for direction in DIRECTIONS:
        counts = ", ".join(f"{s} {v['pairs']} ({v['aligned']} aligned)" for s, v in summary[direction].items())
        print(f"pairing {direction}: {counts}")
    for warning in warnings:
        print(f"  warning: {warning}")
    return summary


def leaked_sources(tiles: pd.DataFrame) -> list[str]:
    """Sources whose tiles fall in more than one split (empty unless the dataset fixed such a split)."""
    per_source = tiles.groupby(["class", "source"])["split"].nunique()
    return [f"{c}/{s}" for (c, s), n in per_source.items() if n > 1]
