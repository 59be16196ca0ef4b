"""Score stage: how close generated images are to real ones, always beside reference levels.

For each direction the test-split outputs of the generate stage are scored three ways:

* **aligned** - each output against its own ground truth (the other modality of the same
  view), where the data has one: Colour-SSIM, greyscale SSIM and PSNR (the ``ms_ssim`` column
  stays empty: MS-SSIM is not computed, see ``MS_SSIM_NOTE``);
* **set-to-set** (the paper's protocol) - each output against every real test image of its
  class; the mean Colour-SSIM over all those pairs;
* **nearest-real** - each output against its best match among the real test images of its class.

The same three scores are computed for reference candidates built from the training split, so
every score has levels to be read against (on unaligned real data a flat colour can beat real
images, see ``../shared/data/vitac_cloth11/SOURCE.md``):

* ``real_train`` - real training images of the class (the real-vs-real level);
* ``flat_mean_colour`` - a flat image of the class's mean training colour;
* ``mean_image`` - the class's mean training image;
* ``nearest_neighbour`` - the training target whose input is closest (L2 in pixels) to the test input.

The flat and mean images use the class label, which the generator never sees, so they are
conservative (strong) baselines.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from PIL import Image

from vtgen.io.tables import GENERATED_COLUMNS
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.core.metrics import colour_ssim, grey_ssim, pairwise_colour_ssim, psnr
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.io.tables import candidate_label, CANDIDATES

ALIGNED_METRICS = ["colour_ssim", "grey_ssim", "psnr", "ms_ssim"]
SET_METRICS = ["set_colour_ssim", "nearest_real_colour_ssim"]
SCORE_COLUMNS = ["direction", "scope", "candidate", "class", "image", "ground_truth_path",
                 *ALIGNED_METRICS, *SET_METRICS, "nearest_real_path"]
DATA_RANGE = 255.0
MS_SSIM_NOTE = ("not computed: vtgen.core.metrics has one SSIM implementation, the single-scale Colour-SSIM kernel, "
                "and no multi-scale path; MS-SSIM (Wang, Simoncelli & Bovik 2003) needs images of at least 161 px "
                "(the 11 px window at its fifth scale, after four halvings), and these images are {size} px")


def _image_side(path: str) -> int:
    with Image.open(path) as image:
        return image.width


def _channels_last(images: torch.Tensor) -> np.ndarray:
    return images.permute(0, 2, 3, 1).numpy()


def aligned_scores(candidates: np.ndarray, truths: np.ndarray) -> dict[str, np.ndarray]:
    """Per-image scores of N x H x W x 3 uint8 ``candidates`` against their own ``truths``.

    MS-SSIM is not computed (``MS_SSIM_NOTE``): its column is NaN.
    """
    return {"colour_ssim": colour_ssim(candidates, truths, DATA_RANGE),
            "grey_ssim": grey_ssim(candidates, truths, DATA_RANGE),
            "psnr": psnr(candidates, truths, DATA_RANGE),
            "ms_ssim": np.full(len(candidates), np.nan)}


def set_scores(candidates: np.ndarray, reals: np.ndarray, batch_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Set-to-set protocol: per candidate, the mean Colour-SSIM against every real image, the best
    one (nearest-real score) and the index of that best real image."""
    matrix = pairwise_colour_ssim(candidates, reals, DATA_RANGE, batch_size=batch_size)
    return matrix.mean(axis=1), matrix.max(axis=1), matrix.argmax(axis=1)


def reference_candidates(test_inputs: torch.Tensor, test_classes: np.ndarray, train_inputs: torch.Tensor,
                         train_targets: torch.Tensor, train_classes: np.ndarray) -> dict[str, torch.Tensor]:
    """Baseline outputs, one per test input (uint8 N x 3 x S x S): nearest-neighbour retrieval,
    the class's mean training image and a flat image of the class's mean training colour."""
    distances = torch.cdist(test_inputs.flatten(1).double(), train_inputs.flatten(1).double())
    nearest = train_targets[distances.argmin(dim=1)]
    mean_image = torch.empty_like(nearest)
    flat = torch.empty_like(nearest)
    for name in np.unique(test_classes):
        in_class = torch.from_numpy(train_classes == name)
        if not in_class.any():
            raise ValueError(f"class '{name}' has test images but no training targets to build reference levels from")
        targets = train_targets[in_class].double()
        rows = torch.from_numpy(test_classes == name)
        mean_image[rows] = targets.mean(dim=0).round().to(torch.uint8)
        flat[rows] = targets.mean(dim=(0, 2, 3)).round().to(torch.uint8)[:, None, None]
    return {"nearest_neighbour": nearest, "mean_image": mean_image, "flat_mean_colour": flat}


def score_candidates(direction: str, scope: str, candidate: str, images: torch.Tensor, classes: np.ndarray,
                     names: list[str], truth_paths: list[str], real_test: dict[str, tuple[np.ndarray, list[str]]],
                     size: int, batch_size: int) -> pd.DataFrame:
    """Score one candidate set of a direction: aligned where a ground truth is listed, and set-to-set
    and nearest-real against ``real_test`` ({class: (images N x S x S x 3, paths)})."""
    table = pd.DataFrame({"direction": direction, "scope": scope, "candidate": candidate, "class": classes,
                          "image": names, "ground_truth_path": truth_paths})
    for metric in ALIGNED_METRICS + SET_METRICS:
        table[metric] = np.nan
    table["nearest_real_path"] = ""
    pixels = _channels_last(images)
    has_truth = np.array([bool(p) for p in truth_paths])
    if has_truth.any():
        truths = _channels_last(read_tiles([p for p in truth_paths if p], size))
        for metric, values in aligned_scores(pixels[has_truth], truths).items():
            table.loc[has_truth, metric] = values
    for name in np.unique(classes):
        rows = classes == name
        if name not in real_test:
            continue
        reals, real_paths = real_test[name]
        mean, best, best_index = set_scores(pixels[rows], reals, batch_size)
        table.loc[rows, "set_colour_ssim"] = mean
        table.loc[rows, "nearest_real_colour_ssim"] = best
        table.loc[rows, "nearest_real_path"] = [real_paths[i] for i in best_index]
    return table[SCORE_COLUMNS]


def score_direction(direction: str, generated: pd.DataFrame, splits: pd.DataFrame, pairs: pd.DataFrame,
                    batch_size: int) -> pd.DataFrame:
    """Per-image scores of one direction: every scope's generated test outputs and the reference candidates."""
    target_modality = DIRECTIONS[direction][1]
    test = generated[generated["split"] == "test"].sort_values(["scope", "class", "input_path"])
    if test.empty:
        raise ValueError(f"{direction}: generated.parquet lists no test-split outputs to score")
    size = _image_side(test["output_path"].iloc[0])
    real = splits[splits["modality"] == target_modality]
    real_test = {}
    for name, group in real[real["split"] == "test"].sort_values("path").groupby("class", sort=True):
        real_test[name] = (_channels_last(read_tiles(list(group["path"]), size)), list(group["path"]))
    tables = []
    for scope, rows in test.groupby("scope", sort=True):
        tables.append(score_candidates(
            direction, scope, "generated", read_tiles(list(rows["output_path"]), size), rows["class"].to_numpy(),
            list(rows["output_path"]), list(rows["ground_truth_path"].fillna("")), real_test, size, batch_size))

    inputs = test.drop_duplicates("input_path")
    train_pairs = pairs[pairs["split"] == "train"].sort_values("input_path")
    references = reference_candidates(
        read_tiles(list(inputs["input_path"]), size), inputs["class"].to_numpy(),
        read_tiles(list(train_pairs["input_path"]), size), read_tiles(list(train_pairs["target_path"]), size),
        train_pairs["class"].to_numpy())
    for candidate, images in references.items():
        names = [f"{candidate}:{p}" for p in inputs["input_path"]]
        tables.append(score_candidates(direction, "-", candidate, images, inputs["class"].to_numpy(), names,
                                       list(inputs["ground_truth_path"].fillna("")), real_test, size, batch_size))

    real_train = real[(real["split"] == "train") & real["class"].isin(set(inputs["class"]))].sort_values("path")
    tables.append(score_candidates(
        direction, "-", "real_train", read_tiles(list(real_train["path"]), size), real_train["class"].to_numpy(),
        list(real_train["path"]), [""] * len(real_train), real_test, size, batch_size))
    return pd.concat(tables, ignore_index=True)


def by_class(scores: pd.DataFrame) -> pd.DataFrame:
    """Mean of every score per direction, scope, candidate and class, plus an ``(all)`` row per
    candidate averaging over images; ``images`` counts the rows averaged."""
    keys = ["direction", "scope", "candidate"]
    metrics = ALIGNED_METRICS + SET_METRICS
    per_class = scores.groupby(keys + ["class"], sort=True)[metrics].mean()
    per_class["images"] = scores.groupby(keys + ["class"], sort=True).size()
    overall = scores.groupby(keys, sort=True)[metrics].mean()
    overall["images"] = scores.groupby(keys, sort=True).size()
    overall["class"] = "(all)"
    table = pd.concat([per_class.reset_index(), overall.reset_index()], ignore_index=True)
    order = {name: i for i, name in enumerate(CANDIDATES)}
    table["_order"] = table["candidate"].map(order)
    return table.sort_values(["direction", "class", "_order", "scope"]).drop(columns="_order").reset_index(drop=True)


def headline(table: pd.DataFrame) -> dict:
    """{direction: {candidate[/scope]: {metric: mean over images}}} from the ``(all)`` rows of ``by_class``."""
    result: dict = {}
    for row in table[table["class"] == "(all)"].itertuples(index=False):
        name = candidate_label(row.candidate, row.scope)
        values = {m: (None if pd.isna(getattr(row, m)) else round(float(getattr(row, m)), 6))
                  for m in ALIGNED_METRICS + SET_METRICS}
        values["images"] = int(row.images)
        result.setdefault(row.direction, {})[name] = values
    return result


def run_score(params: dict, pairs_dir: str | Path, generated_root: str | Path, out_dir: str | Path) -> dict:
    """Score every direction under ``generated_root``; write ``scores`` (per image), ``by_class``
    (parquet and CSV) and ``summary.json`` to ``out_dir``."""
    pairs_dir, generated_root = Path(pairs_dir), Path(generated_root)
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    tables = []
    for direction in DIRECTIONS:
        generated = read_table(generated_root / direction / "generated.parquet", GENERATED_COLUMNS,
                               f"the {direction} output table of the generate stage")
        pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
        tables.append(score_direction(direction, generated, splits, pairs, params["score"]["batch_size"]))
    scores = pd.concat(tables, ignore_index=True)
    classes_table = by_class(scores)
    size = _image_side(scores.loc[scores["candidate"] == "generated", "image"].iloc[0])
    summary = {
        "synthetic": params["dataset"]["source"] == "synthetic",
        "image_size": size,
        "candidates": CANDIDATES,
        "aligned_pairs": {d: int(scores[(scores["direction"] == d) & (scores["candidate"] == "generated")]
                                 ["colour_ssim"].notna().sum()) for d in DIRECTIONS},
        "ms_ssim": MS_SSIM_NOTE.format(size=size),
        "scores": headline(classes_table),
    }
    with atomic_output_dir(out_dir) as tmp:
        for name, table in (("scores", scores), ("by_class", classes_table)):
            table.to_parquet(tmp / f"{name}.parquet", index=False)
            table.to_csv(tmp / f"{name}.csv", index=False, float_format="%.6f")
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for direction, levels in summary["scores"].items():
        parts = [f"{name} {v['set_colour_ssim']:.3f}" for name, v in levels.items() if v["set_colour_ssim"] is not None]
        print(f"score {direction}: set-to-set Colour-SSIM " + ", ".join(parts))
    return summary
