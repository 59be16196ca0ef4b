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
conservative (strong) baselines. Every mean in ``by_class`` comes with its n and a 95% bootstrap
interval over test groups (:func:`vtgen.core.metrics.bootstrap_interval`).

**Distribution metrics** (``distribution.csv``; definitions in :mod:`vtgen.core.distribution` and
docs/evaluation.md). Set-to-set SSIM rewards blur, so each direction is also scored as a
distribution: the real test images of the target modality are split by group into halves A and B;
every candidate set is compared with B: ``real_heldout`` (A: the real-vs-real level),
``generated``, ``nearest_neighbour``, ``mean_image``, ``flat_mean_colour`` and ``blurred_real``
(A under a Gaussian blur of sigma = side / 32). A candidate larger than A is subsampled (seeded) to
A's size, so every row compares sets of equal n (FID is biased by n). Features come from two
encoders available offline: ``classifier`` (the classify stage's real-only classifier of the target
modality, its penultimate layer) and ``random`` (a fixed random-weight CNN); the power-spectrum
distance works on pixels. Per view: KID, FID, the classifier two-sample test, precision, recall,
density and coverage. ``memorisation.csv`` compares each generated test image's distance to the
training targets with that of real held-out images (classifier features and pixels).
``differences.csv`` holds generated's KID and FID minus each baseline's on the same reference, with
paired intervals (the reference's own noise cancels in a difference; two sets' separate intervals
both carry it), and the same for real held-out half A in generated's place: how far real images
themselves beat each baseline at this n, the most a generator could show. The class-wise KID (``kid_classwise``, :func:`classwise_kid_rows`) averages each class's
KID over classes, so a set that draws one class's look for another cannot hide in the pooled mixture.
``summary.json`` holds one verdict per direction and metric family.
"""

from __future__ import annotations

import hashlib
import json
from concurrent.futures import ThreadPoolExecutor
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from PIL import Image

from vtgen.io.tables import GENERATED_COLUMNS
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.core import distribution as dist
from vtgen.core import fixed_pattern as fixed
from vtgen.core import following as follow
from vtgen.core.classifier import wilson_interval
from vtgen.core.metrics import bootstrap_interval, colour_ssim, grey_ssim, pairwise_colour_ssim, psnr
from vtgen.io.classifiers import load_classifier
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles, write_png
from vtgen.io.tables import candidate_label, CANDIDATES

ALIGNED_METRICS = ["colour_ssim", "grey_ssim", "psnr", "ms_ssim"]
SET_METRICS = ["set_colour_ssim", "nearest_real_colour_ssim"]
SCORE_COLUMNS = ["direction", "scope", "candidate", "class", "image", "group", "ground_truth_path",
                 *ALIGNED_METRICS, *SET_METRICS, "nearest_real_path"]
INTERVAL_METRICS = ["colour_ssim", "grey_ssim", "psnr", "set_colour_ssim", "nearest_real_colour_ssim"]
DISTRIBUTION_COLUMNS = ["direction", "scope", "class", "candidate", "view", "metric", "value", "low", "high",
                        "n", "n_reference"]
MEMORISATION_COLUMNS = ["direction", "class", "view", "candidate", "rate", "rate_low", "rate_high",
                        "nearest_is_train_share", "n", "n_train", "train_groups"]
# the generated test images nearest to a training image, each beside that image (nearest_training_direction)
NEAREST_TRAINING_COLUMNS = ["direction", "view", "rank", "generated_path", "train_path", "generated_class",
                            "train_class", "distance", "threshold", "flagged"]
NEAREST_SHOWN = 8  # pairs per direction: enough to tell copies from look-alikes at a glance
# a candidate (generated, or real held-out half A in its place) minus each trivial baseline, both against the
# same reference (real held-out half B): paired intervals
DIFFERENCE_COLUMNS = ["direction", "scope", "candidate", "view", "metric", "baseline", "value", "low", "high", "n",
                      "n_baseline", "n_reference"]
DIVERSITY_COLUMNS = ["direction", "class", "view", "ratio", "low", "high", "generated_spread", "real_spread", "n",
                     "n_real", "interval"]
# per class: images whose brightness lies outside the class's real training images' range (brightness_direction)
BRIGHTNESS_COLUMNS = ["direction", "class", "candidate", "outside", "n", "share", "low", "high", "median", "darker",
                      "lighter", "real_low", "real_high"]
BRIGHTNESS_FAMILY = "brightness range (pixels)"
# per candidate: the share of fine detail at the same place in every image, and one-pixel dots (fixed_pattern_direction)
FIXED_PATTERN_COLUMNS = ["direction", "candidate", "share", "low", "high", "rms", "rms_low", "rms_high", "dots",
                         "dots_low", "dots_high", "n", "peak", "threshold"]
FIXED_PATTERN_FAMILY = "fixed pattern (pixels)"
# the input-following check: per class, candidate generated (outputs against their inputs) or real_paired (the real
# targets of the same inputs, where every input has one: aligned data), a Mantel correlation (following_direction)
FOLLOWING_COLUMNS = ["direction", "class", "candidate", "view", "r", "null_low", "null_high", "p", "n", "pairs"]
FOLLOWING_FAMILY = "input following ({view})"
FOLLOWING_PERMUTATIONS = 999
FOLLOWING_LEVEL = 0.05  # one-sided: outputs follow their inputs when the permutation p is below it
# a fixed pattern is a warning when its share lies this much above real held-out's (beyond both intervals too) and its
# RMS is at least FIXED_RMS_FLOOR grey levels: vt60 V2T's lattice of squares, plain in its grids, has share 0.23-0.36
# (real 0.015) and RMS 1.6-2.0; vt60 T2V's (0.022, RMS 0.85) and the embedded default V2T's (0.14, RMS 0.65) do not
# show (benchmarks/README.md, Sixty-fifth round)
FIXED_SHARE_MARGIN = 0.1
FIXED_RMS_FLOOR = 1.0
DOT_FACTOR = 3.0  # the threshold: this many times the real training images' largest dot-map value (their texture's own)
DOT_FLOOR = 3.0  # grey levels: the threshold never goes below it, so near-flat real images do not flag faint detail
FIXED_PATTERN_RESAMPLES = 200
# a warning's reading where some class trained on one split group: copying and learning the class look alike there
ONE_GROUP_CAVEAT = ("; at least one class has a single training group (one instance or session), so a generator that "
                    "learns that class can only reproduce that group's look, and held-out real images come from "
                    "other groups: here the check cannot tell copying from learning the class")
BASELINES = ["nearest_neighbour", "mean_image", "flat_mean_colour", "blurred_real"]
# metric: (family shown in verdicts, True when lower is better, target value for "better" = closer to it)
DISTRIBUTION_METRICS = {"kid": ("KID", True), "fid": ("FID", True), "two_sample": ("two-sample accuracy", True),
                        "precision": ("precision", False), "recall": ("recall", False),
                        "density": ("density", False), "coverage": ("coverage", False),
                        "spectrum": ("power-spectrum distance", True),
                        "kid_classwise": ("class-wise KID", True)}
VERDICT_METRICS = [("kid", "classifier"), ("kid", "random"), ("kid_classwise", "classifier"), ("fid", "classifier"),
                   ("fid", "random"), ("two_sample", "classifier"), ("coverage", "classifier"), ("spectrum", "pixels")]
KID_SUBSETS = 50
# below this many images per set a two-sample accuracy's interval spans most of [0, 1] (n = 9 + 9:
# about +-0.2), so it is not computed (a class of the default run has 6 held-out images per half)
TWO_SAMPLE_MIN_IMAGES = 10
SCORE_SEED = 0  # halves, subsamples and bootstrap resamples: fixed, so a rerun on the same inputs gives the same numbers
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
    # exact integer squared distances: the same nearest (first of equals) as the Euclidean distance
    nearest = train_targets[dist.pixel_squared_distances(test_inputs, train_inputs).argmin(dim=1)]
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


def _cached_set_scores(candidates: np.ndarray, reals: np.ndarray, batch_size: int,
                       cache: dict | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`set_scores`, each distinct candidate image computed once: ``cache`` maps an image's key
    (:func:`image_keys`) to its (mean, best, best index) against these ``reals`` (one cache per reals)."""
    if cache is None:
        return set_scores(candidates, reals, batch_size)
    keys = [hashlib.blake2b(c.tobytes(), digest_size=16).digest() for c in candidates]
    missing: dict = {}
    for i, key in enumerate(keys):
        if key not in cache and key not in missing:
            missing[key] = i
    if missing:
        values = set_scores(np.ascontiguousarray(candidates[list(missing.values())]), reals, batch_size)
        cache.update((key, (values[0][j], values[1][j], values[2][j])) for j, key in enumerate(missing))
    mean, best, index = zip(*(cache[key] for key in keys)) if keys else ((), (), ())
    return np.array(mean, dtype=np.float64), np.array(best, dtype=np.float64), np.array(index, dtype=np.int64)


class TileReader:
    """:func:`vtgen.io.images.read_tiles` with each file decoded once per stage run: the directions and
    candidates read the same tiles (one modality's test tiles are one direction's real images and ground
    truths and the other's inputs; the training targets are ``real_train``). A tile's decoding and resizing
    do not depend on the others read with it, so the tensors are those of ``read_tiles``; its errors are
    raised for the files not read before (the size check compares those, per half: a call's new files
    are read in two halves in two threads)."""

    def __init__(self):
        self.store: dict = {}

    def __call__(self, paths: list[str], size: int) -> torch.Tensor:
        missing = list(dict.fromkeys(p for p in paths if (p, size) not in self.store))
        if missing:
            # two halves in two threads (the decoders release the GIL); each half is checked as read_tiles checks
            halves = [missing[:len(missing) // 2], missing[len(missing) // 2:]] if len(missing) >= 64 else [missing]
            with ThreadPoolExecutor(len(halves)) as pool:
                for half, tiles in zip(halves, pool.map(lambda part: read_tiles(part, size), halves)):
                    self.store.update(zip(((p, size) for p in half), tiles))
        if not paths:
            return read_tiles([], size)
        return torch.stack([self.store[(p, size)] for p in paths])


def score_candidates(direction: str, scope: str, candidate: str, images: torch.Tensor, classes: np.ndarray,
                     names: list[str], groups: list[str], truth_paths: list[str],
                     real_test: dict[str, tuple[np.ndarray, list[str]]], size: int, batch_size: int,
                     ssim_cache: dict | None = None, tiles=read_tiles) -> pd.DataFrame:
    """Score one candidate set of a direction: aligned where a ground truth is listed, and set-to-set
    and nearest-real against ``real_test`` ({class: (images N x S x S x 3, paths)}). ``groups`` are the
    test groups the images come from (the unit of the bootstrap intervals). ``ssim_cache`` ({class: {}},
    shared by the candidates of one direction) computes each distinct image's set-to-set scores once:
    the nearest-neighbour outputs are training tiles ``real_train`` also scores, and the mean and flat
    baselines repeat one image per class. ``tiles`` reads the ground truths (e.g. a :class:`TileReader`)."""
    table = pd.DataFrame({"direction": direction, "scope": scope, "candidate": candidate, "class": classes,
                          "image": names, "group": groups, "ground_truth_path": truth_paths})
    for metric in ALIGNED_METRICS + SET_METRICS:
        table[metric] = np.nan
    table["nearest_real_path"] = ""
    pixels = _channels_last(images)
    has_truth = np.array([bool(p) for p in truth_paths])
    if has_truth.any():
        truths = _channels_last(tiles([p for p in truth_paths if p], size))
        for metric, values in aligned_scores(pixels[has_truth], truths).items():
            table.loc[has_truth, metric] = values
    for name in np.unique(classes):
        rows = classes == name
        if name not in real_test:
            continue
        reals, real_paths = real_test[name]
        mean, best, best_index = _cached_set_scores(
            pixels[rows], reals, batch_size, None if ssim_cache is None else ssim_cache.setdefault(name, {}))
        table.loc[rows, "set_colour_ssim"] = mean
        table.loc[rows, "nearest_real_colour_ssim"] = best
        table.loc[rows, "nearest_real_path"] = [real_paths[i] for i in best_index]
    return table[SCORE_COLUMNS]


def score_direction(direction: str, generated: pd.DataFrame, splits: pd.DataFrame, pairs: pd.DataFrame,
                    batch_size: int, sets: dict | None = None, tiles=None) -> pd.DataFrame:
    """Per-image scores of one direction: every scope's generated test outputs and the reference candidates.
    When ``sets`` is a dict it receives the images scored, for the distribution metrics:
    ``{(candidate, scope): (uint8 images, classes, groups)}`` plus ``"real_test"`` and ``"real_train"``, and
    ``"paths"``: ``{("generated", scope) or "real_train": the files of those images, in their order}``, and
    ``"inputs"`` and ``"truths"``: ``{scope: the input images of that scope's generated images, in their order}``
    and the same for their real targets (None where some input has none: class pairs).
    ``tiles`` reads the tiles (a :class:`TileReader` shared by the directions; default ``read_tiles``)."""
    sets = {} if sets is None else sets
    sets["paths"] = {}
    read = read_tiles if tiles is None else tiles
    target_modality = DIRECTIONS[direction][1]
    group_of = dict(zip(splits["path"], splits["group"]))
    test = generated[generated["split"] == "test"].sort_values(["scope", "class", "input_path"])
    if test.empty:
        raise ValueError(f"{direction}: generated.parquet lists no test-split outputs to score")
    size = _image_side(test["output_path"].iloc[0])
    real = splits[splits["modality"] == target_modality]
    real_test = {}
    test_rows = real[real["split"] == "test"].sort_values(["class", "path"])
    test_images = read(list(test_rows["path"]), size)
    sets["real_test"] = (test_images, test_rows["class"].to_numpy(), test_rows["group"].to_numpy())
    for name in sorted(set(test_rows["class"])):
        rows_of = (test_rows["class"] == name).to_numpy()
        real_test[name] = (_channels_last(test_images[torch.tensor(rows_of)]), list(test_rows["path"][rows_of]))
    tables, ssim_cache = [], {}
    for scope, rows in test.groupby("scope", sort=True):
        images, classes = read(list(rows["output_path"]), size), rows["class"].to_numpy()
        groups = [group_of.get(p, p) for p in rows["input_path"]]
        sets[("generated", scope)] = (images, classes, np.array(groups))
        sets["paths"][("generated", scope)] = list(rows["output_path"])
        truths = list(rows["ground_truth_path"].fillna(""))
        sets.setdefault("inputs", {})[scope] = read(list(rows["input_path"]), size)
        sets.setdefault("truths", {})[scope] = read(truths, size) if all(truths) else None
        tables.append(score_candidates(
            direction, scope, "generated", images, classes, list(rows["output_path"]), groups,
            list(rows["ground_truth_path"].fillna("")), real_test, size, batch_size, ssim_cache, read))

    inputs = test.drop_duplicates("input_path")
    train_pairs = pairs[pairs["split"] == "train"].sort_values("input_path")
    references = reference_candidates(
        read(list(inputs["input_path"]), size), inputs["class"].to_numpy(),
        read(list(train_pairs["input_path"]), size), read(list(train_pairs["target_path"]), size),
        train_pairs["class"].to_numpy())
    input_groups = [group_of.get(p, p) for p in inputs["input_path"]]
    for candidate, images in references.items():
        names = [f"{candidate}:{p}" for p in inputs["input_path"]]
        sets[(candidate, "-")] = (images, inputs["class"].to_numpy(), np.array(input_groups))
        tables.append(score_candidates(direction, "-", candidate, images, inputs["class"].to_numpy(), names,
                                       input_groups, list(inputs["ground_truth_path"].fillna("")), real_test, size,
                                       batch_size, ssim_cache, read))

    real_train = real[(real["split"] == "train") & real["class"].isin(set(inputs["class"]))].sort_values("path")
    train_images = read(list(real_train["path"]), size)
    sets["real_train"] = (train_images, real_train["class"].to_numpy(), real_train["group"].to_numpy())
    sets["paths"]["real_train"] = list(real_train["path"])
    tables.append(score_candidates(
        direction, "-", "real_train", train_images, real_train["class"].to_numpy(),
        list(real_train["path"]), list(real_train["group"]), [""] * len(real_train), real_test, size, batch_size,
        ssim_cache, read))
    return pd.concat(tables, ignore_index=True)


def _with_intervals(frame: pd.DataFrame, keys: list[str], seed: int) -> pd.DataFrame:
    """Means of every score per ``keys``, ``images`` (n), ``groups`` (test groups among them) and, for
    INTERVAL_METRICS, ``<metric>_low``/``<metric>_high``: the 95% bootstrap interval over groups."""
    rows = []
    for key, group in frame.groupby(keys, sort=True):
        row = dict(zip(keys, key if isinstance(key, tuple) else (key,)))
        row.update({m: group[m].mean() for m in ALIGNED_METRICS + SET_METRICS})
        row["images"], row["groups"] = len(group), int(group["group"].nunique())
        for metric in INTERVAL_METRICS:
            row[f"{metric}_low"], row[f"{metric}_high"] = bootstrap_interval(
                group[metric].to_numpy(), group["group"].to_numpy(), seed=seed)
        rows.append(row)
    return pd.DataFrame(rows)


def by_class(scores: pd.DataFrame, seed: int = 0) -> pd.DataFrame:
    """Mean of every score per direction, scope, candidate and class, plus an ``(all)`` row per
    candidate averaging over images; ``images`` counts the rows averaged, ``groups`` the test groups
    they come from, and ``<metric>_low``/``_high`` bound the 95% bootstrap interval over those groups."""
    keys = ["direction", "scope", "candidate"]
    per_class = _with_intervals(scores, keys + ["class"], seed)
    overall = _with_intervals(scores, keys, seed)
    overall["class"] = "(all)"
    table = pd.concat([per_class, overall], ignore_index=True)
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


def heldout_halves(classes: np.ndarray, groups: np.ndarray, seed: int) -> tuple[np.ndarray, bool]:
    """Boolean mask of half A of the real test images (the rest is B), per class by whole groups
    (shuffled with ``seed``, dealt alternately); a class with a single group is halved by image
    instead. Returns (mask, True when every class could be halved by group)."""
    rng = np.random.default_rng(seed)
    in_a = np.zeros(len(classes), dtype=bool)
    by_group = True
    for name in np.unique(classes):
        rows = np.flatnonzero(classes == name)
        units = np.unique(groups[rows])
        if len(units) >= 2:
            chosen = set(rng.permutation(units)[0::2])
            in_a[rows] = [g in chosen for g in groups[rows]]
        else:
            by_group = False
            in_a[rows[rng.permutation(len(rows))[0::2]]] = True
    return in_a, by_group


def _subsample(count: int, limit: int, rng: np.random.Generator) -> np.ndarray:
    return np.arange(count) if count <= limit else np.sort(rng.choice(count, size=limit, replace=False))


def image_keys(images: torch.Tensor) -> list[bytes]:
    """One key per image: a BLAKE2b digest of its bytes, so equal images share a key."""
    array = images.contiguous().numpy()
    return [hashlib.blake2b(a.tobytes(), digest_size=16).digest() for a in array]


class FeatureCache:
    """Features of each distinct image, computed once per view and reused by every candidate set, class
    and metric of a direction (issue 26).

    Views: every encoder of ``encoders`` (``classifier``, ``random``), ``spectrum`` (each image's log radial
    power profile, :func:`vtgen.core.distribution.log_spectra`) and ``grey`` (64 px grey pixels, the
    diversity ratio's pixel view). Images are keyed by their bytes (:func:`image_keys`), so the
    nearest-neighbour outputs (training tiles that ``real_train`` also holds) and the one mean image
    a class repeats are encoded once. ``encoded`` counts the images each view computed."""

    def __init__(self, encoders: dict):
        self.encoders = encoders
        self.views = [*encoders, "spectrum", "grey"]
        self.store: dict = {view: {} for view in self.views}
        self.encoded = dict.fromkeys(self.views, 0)

    def _compute(self, view: str, images: torch.Tensor) -> torch.Tensor:
        if view == "spectrum":
            return torch.from_numpy(dist.log_spectra(images))
        if view == "grey":
            return dist.grey_pixels(images)
        return dist.image_features(self.encoders[view], images)

    def __call__(self, view: str, images: torch.Tensor, keys: list[bytes] | None = None,
                 rows: np.ndarray | None = None) -> torch.Tensor:
        """Float64 ``N x D`` features in ``view`` of ``images`` (of ``images[rows]`` when ``rows`` is given);
        ``keys``: the :func:`image_keys` of all of ``images``, if known. Images not seen before are encoded
        together, in one batched pass."""
        keys = image_keys(images) if keys is None else keys
        rows = np.arange(len(images)) if rows is None else np.asarray(rows, dtype=np.int64)
        store, missing = self.store[view], {}
        for i in rows:
            key = keys[i]
            if key not in store and key not in missing:
                missing[key] = int(i)
        if missing:
            values = self._compute(view, images[torch.tensor(list(missing.values()), dtype=torch.long)])
            store.update(zip(missing, values))
            self.encoded[view] += len(missing)
        if len(rows) == 0:
            return torch.empty(0, 0, dtype=torch.float64)
        return torch.stack([store[keys[i]] for i in rows])


def _interval_from_share(value: float, count: int) -> tuple[float, float]:
    return wilson_interval(value, count) if count > 0 and not math.isnan(value) else (math.nan, math.nan)


def kid_subset_size(*sets) -> int:
    """KID's subset size for these sets: half the smallest (at least 2), so that the subsets differ and their
    spread means something; the smallest whole when it has fewer than 4 rows."""
    smaller = min(len(s) for s in sets)
    return max(2, smaller // 2) if smaller >= 4 else smaller


def _set_metrics(reference: dict, candidate: dict, fid_resamples: int,
                 seed: int) -> dict[tuple[str, str], tuple[float, float, float]]:
    """{(view, metric): (value, low, high)} of one candidate set against the reference set; ``reference`` and
    ``candidate`` map a view name to features (``spectrum`` to per-image log spectrum profiles). A metric
    that cannot be computed for these sets (too few images) is NaN. Intervals: KID mean +- 1.96 std over
    subsets, FID a bootstrap over images (``fid_resamples`` draws), two-sample accuracy, precision, recall and
    coverage Wilson intervals on their n (precision over the candidate's images, recall and coverage over the
    reference's; they treat the images as independent, an approximation), none for density and spectrum."""
    out = {}

    def record(view, metric, compute):
        try:
            out[(view, metric)] = compute()
        except ValueError:
            out[(view, metric)] = (math.nan, math.nan, math.nan)

    for view in [v for v in reference if v != "spectrum"]:
        real, fake = reference[view], candidate[view]

        def kid_value():
            mean, std = dist.kid(real, fake, subsets=KID_SUBSETS, subset_size=kid_subset_size(real, fake))
            return mean, mean - 1.96 * std, mean + 1.96 * std

        record(view, "kid", kid_value)
        record(view, "fid", lambda: dist.fid_and_interval(real, fake, fid_resamples, seed))

        def two_sample():
            if min(len(real), len(fake)) < TWO_SAMPLE_MIN_IMAGES:
                raise ValueError("too few images for a two-sample test")
            result = dist.two_sample_test(real, fake)
            return result.accuracy, result.low, result.high

        record(view, "two_sample", two_sample)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # its many small products and comparisons: a second thread costs more than it gives
        try:
            scores = dist.prdc_scores(real, fake)
        except ValueError:
            scores = {}
        finally:
            torch.set_num_threads(threads)
        for metric, count in (("precision", len(fake)), ("recall", len(real)), ("density", 0), ("coverage", len(real))):
            value = scores.get(metric, math.nan)
            out[(view, metric)] = (value, *_interval_from_share(value, count if scores else 0))
    spectrum = float(np.mean(np.abs(reference["spectrum"].mean(dim=0).numpy() - candidate["spectrum"].mean(dim=0).numpy())))
    out[("pixels", "spectrum")] = (spectrum, math.nan, math.nan)
    return out


def _cap_rows(rows: np.ndarray, limit: int, rng: np.random.Generator) -> np.ndarray:
    return rows[_subsample(len(rows), limit, rng)]


def distribution_direction(direction: str, sets: dict, cache: FeatureCache, seed: int, max_per_class: int,
                           fid_resamples: int = 0) -> tuple[pd.DataFrame, dict, pd.DataFrame]:
    """Distribution metrics of every candidate set of one direction against real held-out half B, per
    class and over all classes (``(all)``); see the module docstring. Per class, half B and every
    candidate are subsampled (seeded) to at most ``max_per_class`` images, and a candidate to the size
    of half A's class, so the quadratic metrics cost at most O(max_per_class^2) per class; the
    ``(all)`` row pools the images chosen per class (so its class mix is half A's). Features come
    from ``cache``, each image encoded once. Returns the table (DISTRIBUTION_COLUMNS), facts for
    summary.json (halving, blur sigma, the cap) and the paired differences of the ``(all)`` row
    (DIFFERENCE_COLUMNS, :func:`paired_differences`)."""
    test_images, test_classes, test_groups = sets["real_test"]
    in_a, by_group = heldout_halves(test_classes, test_groups, seed)
    sigma = dist.default_blur_sigma(test_images.shape[-1])
    half_a = np.flatnonzero(in_a)
    blurred = dist.gaussian_blur(test_images[torch.from_numpy(half_a)], sigma)
    test_keys = image_keys(test_images)
    candidates = {("real_heldout", "-"): (test_images, test_classes, test_keys, half_a),
                  ("blurred_real", "-"): (blurred, test_classes[in_a], image_keys(blurred), None)}
    for key, value in sets.items():
        if isinstance(key, tuple):
            candidates[key] = (value[0], value[1], image_keys(value[0]), None)
    views = [*cache.encoders, "spectrum"]
    classes = sorted(set(test_classes))
    chosen_ref, chosen = {}, {}
    for i, name in enumerate(classes):
        ref_rows = np.flatnonzero(~in_a & (test_classes == name))
        chosen_ref[name] = _cap_rows(ref_rows, max_per_class, np.random.default_rng([seed, i, 0]))
        limit = min(int((test_classes[in_a] == name).sum()), max_per_class)
        for k, (key, (_, cand_classes, _, rows_of)) in enumerate(candidates.items()):
            pool = rows_of if rows_of is not None else np.arange(len(cand_classes))
            rows = pool[cand_classes[pool] == name]
            chosen[(name, key)] = _cap_rows(rows, limit, np.random.default_rng([seed, i, k + 1]))

    def features(images, keys, rows):
        return {view: cache(view, images, keys, rows) for view in views}

    # encode every image the loop below reads in one batched pass per set and view (small batches per
    # class cost several times more per image)
    features(test_images, test_keys, np.concatenate([chosen_ref[c] for c in classes] + [half_a]))
    for key, (images, _, keys, _) in candidates.items():
        features(images, keys, np.concatenate([chosen[(c, key)] for c in classes]))

    table_rows, pooled, per_class = [], {}, {}
    for name in [*classes, "(all)"]:
        names = classes if name == "(all)" else [name]
        ref_index = np.concatenate([chosen_ref[c] for c in names])
        if len(ref_index) == 0:
            continue
        ref = features(test_images, test_keys, ref_index)
        for key, (images, _, keys, _) in candidates.items():
            rows = np.concatenate([chosen[(c, key)] for c in names])
            if len(rows) == 0:
                continue
            candidate = features(images, keys, rows)
            if name == "(all)":
                pooled[key] = candidate
            else:
                per_class.setdefault(name, {"reference": ref})[key] = candidate
            for (view, metric), (value, low, high) in _set_metrics(ref, candidate, fid_resamples, seed).items():
                table_rows.append({"direction": direction, "scope": key[1], "class": name, "candidate": key[0],
                                   "view": view, "metric": metric, "value": value, "low": low, "high": high,
                                   "n": len(rows), "n_reference": len(ref_index)})
    facts = {"halves_by": "group" if by_group else "image (some class has a single test group)",
             "blur_sigma": sigma, "half_a": int(in_a.sum()), "half_b": int((~in_a).sum()),
             "max_per_class": int(max_per_class), "fid_resamples": int(fid_resamples)}
    differences = paired_differences(direction, ref, pooled, fid_resamples, seed) if pooled else \
        pd.DataFrame(columns=DIFFERENCE_COLUMNS)
    table = pd.DataFrame(table_rows, columns=DISTRIBUTION_COLUMNS)
    classwise = classwise_kid_differences(direction, per_class, seed)
    table = pd.concat([table, classwise_kid_rows(table)], ignore_index=True)
    if len(classwise):
        differences = pd.concat([differences, classwise], ignore_index=True) if len(differences) else classwise
    return table, facts, differences


def mean_over_classes(values, stds) -> tuple[float, float, float]:
    """(mean, low, high) of per-class values with independent errors: the mean over the C classes and
    mean +- 1.96 sqrt(sum std_c^2) / C (the classes' images are disjoint sets, so their errors add in
    variance)."""
    values, stds = np.asarray(values, float), np.asarray(stds, float)
    mean, std = float(values.mean()), float(np.sqrt((stds ** 2).sum()) / len(values))
    return mean, mean - 1.96 * std, mean + 1.96 * std


def classwise_kid_rows(table: pd.DataFrame) -> pd.DataFrame:
    """Class-wise KID of every candidate set (``kid_classwise``, class ``(all)``): the mean over classes of
    its per-class KID against that class's real held-out half B, an intra-class distance in the manner of
    intra-FID (Miyato & Koyama 2018). Pooled over classes, a set can match the real mixture while each
    class's images look like another class's (one motif drawn for several classes); class-wise it cannot.
    Interval: :func:`mean_over_classes` of the per-class KIDs' std (their interval is mean +- 1.96 std); n
    sums the classes' images. Classes where the KID could not be computed are left out."""
    part = table[(table["metric"] == "kid") & (table["class"] != "(all)") & table["value"].notna()]
    rows = []
    for (scope, candidate, view), group in part.groupby(["scope", "candidate", "view"], sort=False):
        value, low, high = mean_over_classes(group["value"], (group["high"] - group["low"]) / 3.92)
        rows.append({"direction": group["direction"].iloc[0], "scope": scope, "class": "(all)",
                     "candidate": candidate, "view": view, "metric": "kid_classwise", "value": value, "low": low,
                     "high": high, "n": int(group["n"].sum()), "n_reference": int(group["n_reference"].sum())})
    return pd.DataFrame(rows, columns=DISTRIBUTION_COLUMNS)


def classwise_kid_differences(direction: str, per_class: dict, seed: int) -> pd.DataFrame:
    """Class-wise KID of each generated set (and of real held-out half A) minus each trivial baseline's (``kid_classwise`` rows of
    DIFFERENCE_COLUMNS): per class the paired KID difference against that class's reference
    (:func:`vtgen.core.distribution.paired_kid_difference`, subsets as :func:`paired_differences`), then
    :func:`mean_over_classes`. ``per_class``: class -> {"reference": view -> features, (candidate, scope) ->
    view -> features}. A class where the difference cannot be computed (fewer than 2 images in a set) is left
    out of that pair's mean."""
    found: dict = {}
    for name, sets in per_class.items():
        for candidate, scope, baseline, view, real, a, b in _against_baselines(sets["reference"], sets):
            try:
                mean, std = dist.paired_kid_difference(real, a, b, subsets=KID_SUBSETS, seed=seed,
                                                       subset_size=kid_subset_size(real, a, b))
            except ValueError:
                continue
            found.setdefault((candidate, scope, view, baseline), []).append((mean, std, len(a), len(b), len(real)))
    rows = []
    for (candidate, scope, view, baseline), items in found.items():
        means, stds, n, n_base, n_ref = zip(*items)
        value, low, high = mean_over_classes(means, stds)
        rows.append({"direction": direction, "scope": scope, "candidate": candidate, "view": view, "metric": "kid_classwise",
                     "baseline": baseline, "value": value, "low": low, "high": high, "n": sum(n),
                     "n_baseline": sum(n_base), "n_reference": sum(n_ref)})
    return pd.DataFrame(rows, columns=DIFFERENCE_COLUMNS)


def paired_differences(direction: str, reference: dict, candidates: dict, fid_resamples: int,
                       seed: int) -> pd.DataFrame:
    """KID and FID of each generated set, and of real held-out half A in its place (candidate
    ``real_heldout``), minus each trivial baseline's (BASELINES), per feature view, both
    against the same ``reference`` features (real held-out half B, all classes): FID with a paired
    bootstrap (:func:`vtgen.core.distribution.paired_fid_difference`, ``fid_resamples`` draws), KID over
    subsets that share the reference subset (:func:`vtgen.core.distribution.paired_kid_difference`,
    mean +- 1.96 std as the KID rows). A difference whose interval lies below 0 says generated beats that
    baseline beyond the noise of this comparison. ``candidates``: (candidate, scope) -> view -> features."""
    rows = []
    for candidate, scope, baseline, view, real, a, b in _against_baselines(reference, candidates):
        try:
            mean, std = dist.paired_kid_difference(real, a, b, subsets=KID_SUBSETS,
                                                   subset_size=kid_subset_size(real, a, b))
            kid_row = (mean, mean - 1.96 * std, mean + 1.96 * std)
            fid_row = dist.paired_fid_difference(real, a, b, fid_resamples, seed)
        except ValueError:
            continue
        for metric, (value, low, high) in (("kid", kid_row), ("fid", fid_row)):
            rows.append({"direction": direction, "scope": scope, "candidate": candidate, "view": view,
                         "metric": metric, "baseline": baseline, "value": value, "low": low, "high": high, "n": len(a),
                         "n_baseline": len(b), "n_reference": len(real)})
    return pd.DataFrame(rows, columns=DIFFERENCE_COLUMNS)


def _against_baselines(reference: dict, sets: dict):
    """(candidate, scope, baseline, view, reference features, candidate features, baseline features) for every
    generated set of ``sets`` ((candidate, scope) -> view -> features) and real held-out half A, against each
    trivial baseline (BASELINES) it holds, per feature view of ``reference`` (view -> features; the spectrum is
    not a feature view)."""
    for key, generated in sets.items():
        if not isinstance(key, tuple) or key[0] not in ("generated", "real_heldout"):
            continue
        for baseline in BASELINES:
            base = sets.get((baseline, "-"))
            if base is None:
                continue
            for view in [v for v in reference if v != "spectrum"]:
                yield key[0], key[1], baseline, view, reference[view], generated[view], base[view]


def _pooled_generated(sets: dict):
    """The key of the pooled model's generated set (scope 'all'), else the first generated set."""
    return ("generated", "all") if ("generated", "all") in sets else next(
        k for k in sets if isinstance(k, tuple) and k[0] == "generated")


def memorisation_direction(direction: str, sets: dict, cache: FeatureCache) -> pd.DataFrame:
    """Memorisation of the pooled model's generated test images (MEMORISATION_COLUMNS): per class and
    over all, in pixels and in the classifier's features (where ``cache`` has that encoder), beside the
    same rates for real held-out images. Each image's nearest distances (to the training and held-out
    images of each class and of all classes, :func:`vtgen.core.distribution.nearest_distances`) are
    computed once per view and each class reads its rows. ``train_groups``: distinct training split groups
    (instances, sessions) of the class; for ``(all)`` the fewest of any class."""
    key = _pooled_generated(sets)
    gen_classes, train_classes, held_classes = sets[key][1], sets["real_train"][1], sets["real_test"][1]
    groups = pd.Series(sets["real_train"][2]).groupby(pd.Series(train_classes)).nunique()
    train_groups = {**groups.to_dict(), "(all)": int(groups.min()) if len(groups) else 0}
    rows = []
    for view in ["pixels", *[v for v in cache.encoders if v == "classifier"]]:
        g, t, h = (sets[k][0] if view == "pixels" else cache(view, sets[k][0]) for k in (key, "real_train", "real_test"))
        if min(len(g), len(t), len(h)) == 0:
            continue
        # each image's nearest distances per class of the other set, once for all classes
        g_t, g_h = dist.nearest_distances(g, t, train_classes), dist.nearest_distances(g, h, held_classes)
        h_t, h_h = dist.nearest_distances(h, t, train_classes), dist.nearest_distances(h, h, held_classes, True)
        for name in [*sorted(set(gen_classes)), "(all)"]:
            pick = (lambda c: np.ones(len(c), bool)) if name == "(all)" else (lambda c: c == name)
            gi, ti, hi = (torch.from_numpy(np.flatnonzero(pick(c))) for c in (gen_classes, train_classes, held_classes))
            column = None if name == "(all)" else name
            if column is not None and (column not in g_t or column not in g_h):
                continue  # no training or no held-out image of the class
            try:
                result = dist.memorisation_from_nearest(g_t[column][gi], g_h[column][gi], h_t[column][hi],
                                                        h_h[column][hi], len(ti))
            except ValueError:
                continue
            rate_low, rate_high = _interval_from_share(result.rate, len(gi))
            ref_low, ref_high = _interval_from_share(result.reference_rate, len(hi))
            rows.append({"direction": direction, "class": name, "view": view, "candidate": "generated",
                         "rate": result.rate, "rate_low": rate_low, "rate_high": rate_high,
                         "nearest_is_train_share": result.nearest_is_train_share,
                         "n": len(gi), "n_train": len(ti), "train_groups": train_groups.get(name, 0)})
            rows.append({"direction": direction, "class": name, "view": view, "candidate": "real_heldout",
                         "rate": result.reference_rate, "rate_low": ref_low, "rate_high": ref_high,
                         "nearest_is_train_share": result.nearest_is_train_reference,
                         "n": len(hi), "n_train": len(ti), "train_groups": train_groups.get(name, 0)})
    return pd.DataFrame(rows, columns=MEMORISATION_COLUMNS)


def nearest_training_direction(direction: str, sets: dict, cache: FeatureCache,
                               count: int = NEAREST_SHOWN) -> tuple[pd.DataFrame, np.ndarray | None]:
    """The ``count`` generated test images of the pooled model nearest to a real training image, each with that
    image (NEAREST_TRAINING_COLUMNS, ``rank`` 0 the nearest), so a person can see whether the memorisation check's
    flags are copies or look-alikes (e.g. saturated flat fields, which all look alike). The view is the
    memorisation verdict's: the classifier's features where ``cache`` has them, else pixels. ``threshold``: the
    smallest distance of any real held-out image to the training set; ``flagged``: ``distance < threshold``, the
    generated images :func:`vtgen.core.distribution.memorisation` counts. Also the pictures as one uint8
    ``2S x rows*S x 3`` strip: the generated images in rank order on top, their training images below (None
    where there are no rows)."""
    key = _pooled_generated(sets)
    view = "classifier" if "classifier" in cache.encoders else "pixels"
    g, t, h = (sets[k][0] if view == "pixels" else cache(view, sets[k][0]) for k in (key, "real_train", "real_test"))
    if min(len(g), len(t), len(h)) == 0:
        return pd.DataFrame(columns=NEAREST_TRAINING_COLUMNS), None
    nearest, which = dist.pairwise_distances(g, t).min(dim=1)
    threshold = float(dist.pairwise_distances(h, t).min())
    order = np.argsort(nearest.numpy(), kind="stable")[:count]
    gen_paths, train_paths = sets["paths"][key], sets["paths"]["real_train"]
    rows = []
    for rank, i in enumerate(order):
        j = int(which[i])
        rows.append({"direction": direction, "view": view, "rank": rank, "generated_path": gen_paths[i],
                     "train_path": train_paths[j], "generated_class": sets[key][1][i],
                     "train_class": sets["real_train"][1][j], "distance": float(nearest[i]), "threshold": threshold,
                     "flagged": bool(nearest[i] < threshold)})
    shown = torch.from_numpy(order)
    pairs = torch.cat([torch.cat(list(sets[key][0][shown]), dim=2),
                       torch.cat(list(sets["real_train"][0][which[shown]]), dim=2)], dim=1)
    return pd.DataFrame(rows, columns=NEAREST_TRAINING_COLUMNS), pairs.permute(1, 2, 0).contiguous().numpy()


def diversity_direction(direction: str, sets: dict, cache: FeatureCache, seed: int) -> pd.DataFrame:
    """Within-class diversity ratio of the pooled model's generated test images (DIVERSITY_COLUMNS): per
    class, the mean pairwise distance among its generated images over the same among the real test
    images of the class (:func:`vtgen.core.distribution.diversity_ratio`, 95% bootstrap over images), in
    the 64 px grey view (``pixels``) and the classifier's features; then a ``(median)`` row per view,
    the median over classes with a 95% bootstrap interval over classes (``n``: classes)."""
    key = _pooled_generated(sets)
    (gen_images, gen_classes, _), (real_images, real_classes, _) = sets[key], sets["real_test"]
    views = {"pixels": "grey", **{v: v for v in cache.encoders if v == "classifier"}}
    rows = []
    for view, source in views.items():
        ratios = []
        for name in sorted(set(gen_classes) & set(real_classes)):
            g = cache(source, gen_images[torch.from_numpy(gen_classes == name)])
            r = cache(source, real_images[torch.from_numpy(real_classes == name)])
            try:
                result = dist.diversity_ratio(g, r, seed=seed)
            except ValueError:
                continue
            ratios.append(result.ratio)
            rows.append({"direction": direction, "class": name, "view": view, "ratio": result.ratio,
                         "low": result.low, "high": result.high, "generated_spread": result.generated_spread,
                         "real_spread": result.real_spread, "n": result.n_generated, "n_real": result.n_real,
                         "interval": "bootstrap over images"})
        if ratios:
            median, low, high = dist.median_interval(ratios, seed=seed)
            rows.append({"direction": direction, "class": "(median)", "view": view, "ratio": median, "low": low,
                         "high": high, "generated_spread": math.nan, "real_spread": math.nan, "n": len(ratios),
                         "n_real": len(ratios), "interval": "bootstrap over classes"})
    return pd.DataFrame(rows, columns=DIVERSITY_COLUMNS)


def image_brightness(images: torch.Tensor) -> np.ndarray:
    """uint8 N x C x H x W -> float64 N: each image's mean pixel value over its channels and pixels (0-255)."""
    return images.to(torch.float64).mean(dim=(1, 2, 3)).numpy() if len(images) else np.zeros(0)


def brightness_direction(direction: str, sets: dict) -> pd.DataFrame:
    """Brightness check of the pooled model's generated test images (BRIGHTNESS_COLUMNS). Per class, the range
    (lowest to highest) of the mean pixel value (:func:`image_brightness`) of its real training images, the
    images the generator learned the class from; then, for the generated test images and for the real held-out
    images of the class (the reference: a new instance of a class may itself fall outside), how many lie below
    it (``darker``), above it (``lighter``), their share ``outside`` / ``n`` with its 95% Wilson interval, and
    their median brightness. An ``(all)`` row per candidate sums the classes. A generator that draws a class
    darker or lighter than every real image of it (a grey field for a bright touch, a black ground for a red
    floor) shows here where a pooled distribution metric only grows."""
    key = _pooled_generated(sets)
    candidates = {"generated": sets[key], "real_heldout": sets["real_test"]}
    train = pd.Series(image_brightness(sets["real_train"][0])).groupby(sets["real_train"][1])
    ranges = {name: (float(v.min()), float(v.max())) for name, v in train}
    rows = []
    shared = sorted(set(ranges) & set(sets["real_test"][1]) & set(sets[key][1]))  # classes both candidates have
    for candidate, (images, classes, _) in candidates.items():
        values, classes = image_brightness(images), np.asarray(classes)
        class_rows = []
        for name in shared:
            low, high = ranges[name]
            mine = values[classes == name]
            class_rows.append(_brightness_row(direction, name, candidate, int((mine < low).sum()),
                                              int((mine > high).sum()), mine, low, high))
        if class_rows:
            pooled = np.concatenate([values[classes == name] for name in shared])
            class_rows.append(_brightness_row(direction, "(all)", candidate, sum(r["darker"] for r in class_rows),
                                              sum(r["lighter"] for r in class_rows), pooled, math.nan, math.nan))
        rows += class_rows
    return pd.DataFrame(rows, columns=BRIGHTNESS_COLUMNS)


def _brightness_row(direction: str, name: str, candidate: str, darker: int, lighter: int, values: np.ndarray,
                    low: float, high: float) -> dict:
    share = (darker + lighter) / len(values)
    share_low, share_high = wilson_interval(share, len(values))
    return {"direction": direction, "class": name, "candidate": candidate, "outside": darker + lighter,
            "n": len(values), "share": share, "low": share_low, "high": share_high, "median": float(np.median(values)),
            "darker": darker, "lighter": lighter, "real_low": low, "real_high": high}


def brightness_verdicts(brightness: pd.DataFrame) -> list[dict]:
    """One verdict per direction from :func:`brightness_direction`'s ``(all)`` rows: ``warning`` when the generated
    images' share outside their class's real brightness range lies above the real held-out images' share beyond
    both 95% Wilson intervals, else ``ok``. The text names the classes whose generated median lies below (darker)
    or above (lighter) every real training image of the class."""
    found = []
    for direction in sorted(set(brightness["direction"])):
        mine = brightness[brightness["direction"] == direction]
        overall = mine[mine["class"] == "(all)"].set_index("candidate")
        if not {"generated", "real_heldout"} <= set(overall.index):
            continue
        gen, ref = overall.loc["generated"], overall.loc["real_heldout"]
        worse = gen["low"] > ref["high"]
        reading = "above" if worse else "within noise of" if gen["share"] > ref["share"] else "not above"
        per_class = mine[(mine["candidate"] == "generated") & (mine["class"] != "(all)")]
        darker = list(per_class.loc[per_class["median"] < per_class["real_low"], "class"])
        lighter = list(per_class.loc[per_class["median"] > per_class["real_high"], "class"])
        drawn = "".join(f"; {word} than every real training image of the class at the median: {', '.join(names)}"
                        for word, names in (("darker", darker), ("lighter", lighter)) if names)
        found.append({"direction": direction, "family": BRIGHTNESS_FAMILY, "metric": "brightness", "view": "pixels",
                      "status": "warning" if worse else "ok", "generated": float(gen["share"]),
                      "generated_interval": [float(gen["low"]), float(gen["high"])],
                      "real_heldout": float(ref["share"]), "real_heldout_interval": [float(ref["low"]), float(ref["high"])],
                      "n": int(gen["n"]), "n_real": int(ref["n"]), "darker_classes": darker, "lighter_classes": lighter,
                      "text": f"{direction.upper()} {BRIGHTNESS_FAMILY}: {gen['share']:.3f} [{gen['low']:.3f}, "
                              f"{gen['high']:.3f}] of generated test images are darker or lighter (mean pixel value) "
                              f"than every real training image of their class ({reading} the real held-out share "
                              f"{ref['share']:.3f} [{ref['low']:.3f}, {ref['high']:.3f}], 95% Wilson; n = "
                              f"{int(gen['n'])} generated, {int(ref['n'])} real){drawn}"})
    return found


def dot_threshold(real_train: torch.Tensor) -> float:
    """Grey levels above which a set's dot map value counts as a fixed dot: DOT_FACTOR x the largest value of the
    real training images' own :func:`vtgen.core.fixed_pattern.dot_map`, at least DOT_FLOOR."""
    return max(DOT_FACTOR * float(fixed.dot_map(real_train).max()), DOT_FLOOR)


def fixed_pattern_direction(direction: str, sets: dict, seed: int) -> pd.DataFrame:
    """Fixed-pattern check of the pooled model's generated test images, beside the real held-out images
    (FIXED_PATTERN_COLUMNS), each number with a 95% bootstrap interval over images:

    * ``share``: :func:`vtgen.core.fixed_pattern.fixed_share`, the share of the set's fine-detail energy drawn at
      the same place with the same sign in every image (a lattice of squares left by the decoder's upsampling),
      and ``rms``, that pattern's size in grey levels;
    * ``dots``: :func:`vtgen.core.fixed_pattern.fixed_dots`, pixel positions whose mean |grey − 3 x 3 median| over
      the set is above ``threshold`` (:func:`dot_threshold`): one-pixel dots at fixed places; ``peak`` is that
      map's largest value."""
    threshold = dot_threshold(sets["real_train"][0])
    rows = []
    for candidate, images in (("generated", sets[_pooled_generated(sets)][0]), ("real_heldout", sets["real_test"][0])):
        share, dots = fixed.fixed_share(images, FIXED_PATTERN_RESAMPLES, seed), fixed.fixed_dots(images, threshold, FIXED_PATTERN_RESAMPLES, seed)
        rows.append({"direction": direction, "candidate": candidate, "share": share.share, "low": share.low,
                     "high": share.high, "rms": share.rms, "rms_low": share.rms_low, "rms_high": share.rms_high,
                     "dots": dots.count, "dots_low": dots.low, "dots_high": dots.high,
                     "n": share.n, "peak": dots.peak, "threshold": threshold})
    return pd.DataFrame(rows, columns=FIXED_PATTERN_COLUMNS)


def fixed_pattern_verdicts(table: pd.DataFrame) -> list[dict]:
    """One verdict per direction from :func:`fixed_pattern_direction`: ``warning`` when the generated images' fixed
    share lies above the real held-out images' beyond both 95% bootstrap intervals and by at least FIXED_SHARE_MARGIN,
    with a pattern of at least FIXED_RMS_FLOOR grey levels RMS, or their count of fixed dots lies above held-out's
    beyond both intervals; else ``ok``."""
    found = []
    for direction in sorted(set(table["direction"])):
        rows = table[table["direction"] == direction].set_index("candidate")
        gen, ref = rows.loc["generated"], rows.loc["real_heldout"]
        beyond_noise, dots_worse = gen["low"] > ref["high"], gen["dots_low"] > ref["dots_high"]
        large = gen["share"] - ref["share"] >= FIXED_SHARE_MARGIN
        share_worse = beyond_noise and large and gen["rms"] >= FIXED_RMS_FLOOR
        reading = ("above" if share_worse else
                   f"beyond the noise, but less than {FIXED_SHARE_MARGIN:g}, above" if beyond_noise and not large
                   else f"beyond the noise, but too faint to see (RMS under {FIXED_RMS_FLOOR:g} grey level), above"
                   if beyond_noise else "within noise of" if gen["share"] > ref["share"] else "not above")
        dots_reading = "above" if dots_worse else "within noise of" if gen["dots"] > ref["dots"] else "not above"
        found.append({"direction": direction, "family": FIXED_PATTERN_FAMILY, "metric": "fixed_pattern",
                      "view": "pixels", "status": "warning" if share_worse or dots_worse else "ok",
                      "generated": float(gen["share"]), "generated_interval": [float(gen["low"]), float(gen["high"])],
                      "real_heldout": float(ref["share"]), "real_heldout_interval": [float(ref["low"]), float(ref["high"])],
                      "rms": float(gen["rms"]), "dots": int(gen["dots"]), "dots_real_heldout": int(ref["dots"]),
                      "n": int(gen["n"]), "n_real": int(ref["n"]),
                      "text": f"{direction.upper()} {FIXED_PATTERN_FAMILY}: {gen['share']:.3f} [{gen['low']:.3f}, "
                              f"{gen['high']:.3f}] of the generated test images' fine detail is drawn at the same place "
                              f"with the same sign in every image, a pattern of {gen['rms']:.1f} grey levels RMS "
                              f"({reading} the real held-out share {ref['share']:.3f} "
                              f"[{ref['low']:.3f}, {ref['high']:.3f}]); {int(gen['dots'])} [{gen['dots_low']:.0f}, "
                              f"{gen['dots_high']:.0f}] one-pixel dots at fixed places, mean |grey - 3 x 3 median| above "
                              f"{gen['threshold']:.1f} grey levels ({dots_reading} the real held-out count "
                              f"{int(ref['dots'])} [{ref['dots_low']:.0f}, {ref['dots_high']:.0f}]); 95% bootstrap over "
                              f"images, n = {int(gen['n'])} generated, {int(ref['n'])} real"})
    return found


def following_direction(direction: str, sets: dict, seed: int, cache: FeatureCache | None = None,
                        input_encoder=None) -> pd.DataFrame:
    """Input-following check of the pooled model's generated test images (FOLLOWING_COLUMNS): within each class, do
    two outputs lie further apart when their inputs do? :func:`vtgen.core.following.input_following`, per class
    (``r``, ``n``) and an ``(all)`` row with the permutation null's 95% band and one-sided p, in two views:
    ``pixels``, grey LAYOUT_SIDE x LAYOUT_SIDE means of inputs and outputs (where light and dark lie; grain does not
    count), and ``classifier``, where ``cache`` has the target modality's real-only classifier and ``input_encoder``
    is the input modality's (each set in its own modality's features). Where every input has a real target (aligned
    pairs) the same for the real targets (candidate ``real_paired``): how far real data follows."""
    key = _pooled_generated(sets)
    scope, classes = key[1], sets[key][1]
    inputs = sets["inputs"][scope]
    def layout(images: torch.Tensor) -> torch.Tensor:
        return dist.grey_pixels(images, follow.LAYOUT_SIDE)

    views = {"pixels": (layout(inputs), layout)}
    if input_encoder is not None and cache is not None and "classifier" in cache.encoders:
        views["classifier"] = (dist.image_features(input_encoder, inputs), lambda images: cache("classifier", images))
    candidates = {"generated": sets[key][0], "real_paired": sets["truths"][scope]}
    rows = []
    for view, (input_features, features_of) in views.items():
        for candidate, images in candidates.items():
            if images is None:
                continue
            result = follow.input_following(input_features, features_of(images), classes, FOLLOWING_PERMUTATIONS, seed)
            for name, (r, n) in result.per_class.items():
                rows.append({"direction": direction, "class": name, "candidate": candidate, "view": view, "r": r,
                             "null_low": math.nan, "null_high": math.nan, "p": math.nan, "n": n,
                             "pairs": n * (n - 1) // 2})
            rows.append({"direction": direction, "class": "(all)", "candidate": candidate, "view": view, "r": result.r,
                         "null_low": result.null_low, "null_high": result.null_high, "p": result.p,
                         "n": result.images, "pairs": result.pairs})
    return pd.DataFrame(rows, columns=FOLLOWING_COLUMNS)


def following_verdicts(table: pd.DataFrame) -> list[dict]:
    """One verdict per direction and view from :func:`following_direction`'s ``(all)`` rows: ``ok`` when the
    generated outputs follow their inputs beyond chance (permutation p below FOLLOWING_LEVEL); else ``warning`` where
    the real targets of the same inputs do follow them (aligned data: the generator drops what real pairs show),
    ``unresolved`` where there are none (class pairs: nothing in the data says how far a target should follow its
    input)."""
    found = []
    overall = table[table["class"] == "(all)"]
    for (direction, view), rows in overall.groupby(["direction", "view"], sort=True):
        rows = rows.set_index("candidate")
        if "generated" not in rows.index or not math.isfinite(rows.loc["generated", "r"]):
            continue
        gen = rows.loc["generated"]
        follows = gen["p"] < FOLLOWING_LEVEL
        real = rows.loc["real_paired"] if "real_paired" in rows.index else None
        real_follows = real is not None and math.isfinite(real["r"]) and real["p"] < FOLLOWING_LEVEL
        status = "ok" if follows else "warning" if real_follows else "unresolved"
        family = FOLLOWING_FAMILY.format(view=view)
        where = (f"grey {follow.LAYOUT_SIDE} x {follow.LAYOUT_SIDE} means" if view == "pixels"
                 else "each modality's real-only classifier features")
        reading = ("follow their inputs beyond chance" if follows else
                   "do not follow their inputs beyond chance: within a class the generator draws much the same "
                   "whatever the input, or varies with its noise alone")
        reference = (f"; the real targets of the same inputs: r = {real['r']:+.3f} (p = {real['p']:.3f})"
                     if real is not None else "; the data pairs by class only, so no real pair says how far a "
                     "target should follow its input")
        found.append({"direction": direction, "family": family, "metric": f"following_{view}", "view": view,
                      "status": status, "generated": float(gen["r"]),
                      "generated_interval": [float(gen["null_low"]), float(gen["null_high"])],
                      "real_heldout": None if real is None else float(real["r"]), "p": float(gen["p"]),
                      "n": int(gen["n"]), "pairs": int(gen["pairs"]),
                      "text": f"{direction.upper()} {family}: within a class, the distance between two generated test "
                              f"images follows the distance between their inputs with r = {gen['r']:+.3f} (Mantel, "
                              f"{where}; 95% of within-class shuffles give [{gen['null_low']:+.3f}, "
                              f"{gen['null_high']:+.3f}], p = {gen['p']:.3f}; n = {int(gen['n'])} images, "
                              f"{int(gen['pairs'])} pairs): the outputs {reading}{reference}"})
    return found


def _num(value) -> float | None:
    """A finite number rounded to 6 decimals (metrics.json compares exactly), else None."""
    return None if value is None or not math.isfinite(float(value)) else round(float(value), 6)


def goal_metrics(distribution: pd.DataFrame, memorisation: pd.DataFrame, diversity: pd.DataFrame,
                 differences: pd.DataFrame | None = None, following: pd.DataFrame | None = None) -> dict:
    """Issue 24's measurable goals per direction, every value with its 95% interval and n, in plain
    nested dicts for summary.json and the report's metrics.json: the diversity ratios (median over
    classes), recall and coverage of generated and real held-out, KID and FID of generated, real
    held-out and every trivial baseline (classifier view, all classes), and the memorisation rate
    (classifier view; pixels where there is no classifier) of generated and real held-out; under KID and
    FID, ``generated_minus``: generated's value minus each baseline's on the shared reference with its
    paired interval (``differences``, :func:`paired_differences`), and ``real_heldout_minus``: the same for real
    held-out images in generated's place (how far real images beat each baseline at this n); ``following_<view>``: the generated images'
    input-following r (:func:`following_direction`) with the 95% band of within-class shuffles as its interval
    and the permutation ``p``. A value that could not be computed (NaN) is left out."""
    result: dict = {}
    for direction in sorted(set(distribution["direction"]) | set(diversity["direction"])):
        goals: dict = {}
        div = diversity[(diversity["direction"] == direction) & (diversity["class"] == "(median)")]
        for row in div.itertuples(index=False):
            goals[f"diversity_{row.view}"] = {"value": _num(row.ratio), "low": _num(row.low), "high": _num(row.high),
                                              "classes": int(row.n)}
        rows = distribution[(distribution["direction"] == direction) & (distribution["class"] == "(all)")
                            & (distribution["view"] == "classifier")]
        generated_scope = "all" if ((rows["candidate"] == "generated") & (rows["scope"] == "all")).any() else None
        for metric, candidates in (("recall", ["generated", "real_heldout"]), ("coverage", ["generated", "real_heldout"]),
                                   ("kid", ["generated", "real_heldout", *BASELINES]),
                                   ("kid_classwise", ["generated", "real_heldout", *BASELINES]),
                                   ("fid", ["generated", "real_heldout", *BASELINES])):
            part = rows[rows["metric"] == metric]
            entry = {}
            for candidate in candidates:
                match = part[part["candidate"] == candidate]
                if candidate == "generated" and generated_scope:
                    match = match[match["scope"] == generated_scope]
                if len(match):
                    r = match.iloc[0]
                    entry[candidate] = {"value": _num(r["value"]), "low": _num(r["low"]), "high": _num(r["high"]),
                                        "n": int(r["n"]), "n_reference": int(r["n_reference"])}
            if differences is not None and metric in ("kid", "kid_classwise", "fid") and generated_scope:
                mine = differences[(differences["direction"] == direction) & (differences["view"] == "classifier")
                                   & (differences["metric"] == metric)]
                for candidate, scope in (("generated", generated_scope), ("real_heldout", "-")):
                    paired = mine[(mine["candidate"] == candidate) & (mine["scope"] == scope)]
                    if len(paired):
                        entry[f"{candidate}_minus"] = {r["baseline"]: {"value": _num(r["value"]), "low": _num(r["low"]),
                                                                       "high": _num(r["high"]), "n": int(r["n"]),
                                                                       "n_reference": int(r["n_reference"])}
                                                       for _, r in paired.iterrows()}
            if entry:
                goals[f"{metric}_classifier"] = entry
        mem = memorisation[(memorisation["direction"] == direction) & (memorisation["class"] == "(all)")]
        view = "classifier" if (mem["view"] == "classifier").any() else "pixels"
        entry = {r["candidate"]: {"value": _num(r["rate"]), "low": _num(r["rate_low"]), "high": _num(r["rate_high"]),
                                  "n": int(r["n"])}
                 for _, r in mem[mem["view"] == view].iterrows()}
        if entry:
            goals[f"memorisation_{view}"] = entry
        if following is not None:
            mine = following[(following["direction"] == direction) & (following["class"] == "(all)")
                             & (following["candidate"] == "generated")]
            for r in mine.itertuples(index=False):
                goals[f"following_{r.view}"] = {"value": _num(r.r), "low": _num(r.null_low), "high": _num(r.null_high),
                                             "p": _num(r.p), "n": int(r.n)}
        result[direction] = goals
    return _without_none(result)


def _without_none(value):
    """``value`` without None leaves (a NaN that :func:`_num` dropped), so every leaf is a number."""
    if isinstance(value, dict):
        return {k: _without_none(v) for k, v in value.items() if v is not None}
    return value


def _better(metric: str, a: float, b: float) -> bool:
    """True when value ``a`` is better than ``b`` for ``metric`` (two-sample accuracy: closer to 0.5)."""
    if metric == "two_sample":
        return abs(a - 0.5) < abs(b - 0.5)
    lower = DISTRIBUTION_METRICS[metric][1]
    return a < b if lower else a > b


def _separated(a: tuple[float, float], b: tuple[float, float]) -> bool | None:
    """True when two intervals do not overlap, None when either is unknown."""
    if any(math.isnan(v) for v in (*a, *b)):
        return None
    return a[1] < b[0] or b[1] < a[0]


def verdicts(table: pd.DataFrame, memorisation: pd.DataFrame, differences: pd.DataFrame | None = None) -> list[dict]:
    """One verdict per direction and metric family (VERDICT_METRICS, memorisation) for the pooled
    model over all classes: does generated beat every trivial baseline (beyond the intervals where
    the metric has one), and where does it sit between the best baseline (0) and real vs real (1)?
    Status: ``ok``, ``unresolved`` (better, but an interval overlaps), ``warning`` (a baseline is as
    good or better), or ``uninformative`` (real vs real itself does not beat the mean image, flat
    colour or blurred real, so the metric cannot rank on this data; the nearest-neighbour targets
    are real images, which a distribution metric places near real vs real by construction).
    Where ``differences`` holds the paired difference of generated and a baseline (KID, FID), "beyond
    the noise" is read from it (its interval below 0) rather than from the two sets' own intervals."""
    result = []
    differences = pd.DataFrame(columns=DIFFERENCE_COLUMNS) if differences is None else differences
    overall = table[(table["class"] == "(all)")]
    for direction in sorted(set(overall["direction"])):
        for metric, view in VERDICT_METRICS:
            rows = overall[(overall["direction"] == direction) & (overall["metric"] == metric) & (overall["view"] == view)]
            values = {(r.candidate, r.scope): (r.value, r.low, r.high, r.n) for r in rows.itertuples()}
            generated = values.get(("generated", "all")) or next(
                (v for (c, _), v in values.items() if c == "generated"), None)
            real = values.get(("real_heldout", "-"))
            baselines = {c: values[(c, "-")] for c in BASELINES if (c, "-") in values and not math.isnan(values[(c, "-")][0])}
            if generated is None or real is None or not baselines or math.isnan(generated[0]):
                continue
            lost = [c for c, v in baselines.items() if not _better(metric, generated[0], v[0])]
            generated_scope = "all" if ("generated", "all") in values else next(
                (s for (c, s) in values if c == "generated"), None)
            mine = differences[(differences["direction"] == direction) & (differences["metric"] == metric)
                               & (differences["view"] == view)]
            paired, real_paired = ({r.baseline: (r.value, r.low, r.high) for r in part.itertuples() if not math.isnan(r.high)}
                                   for part in (mine[(mine["candidate"] == "generated") & (mine["scope"] == generated_scope)],
                                                mine[mine["candidate"] == "real_heldout"]))
            unresolved = [c for c, v in baselines.items() if c not in lost and (
                paired[c][2] >= 0 if c in paired else _separated(generated[1:3], v[1:3]) is False)]
            best_name, best = min(baselines.items(), key=lambda item: (
                abs(item[1][0] - 0.5) if metric == "two_sample" else item[1][0] * (1 if DISTRIBUTION_METRICS[metric][1] else -1)))
            span = best[0] - real[0]
            gen_gap = best[0] - generated[0]
            if metric == "two_sample":
                span, gen_gap = abs(best[0] - 0.5) - abs(real[0] - 0.5), abs(best[0] - 0.5) - abs(generated[0] - 0.5)
            position = gen_gap / span if span and not math.isnan(span) and abs(span) > 1e-12 else math.nan
            family = f"{DISTRIBUTION_METRICS[metric][0]} ({view})"
            # the nearest-neighbour targets are real training images, so on a distribution metric they sit
            # near the real-vs-real level by construction; the metric is judged on the image-degrading ones
            real_lost = [c for c, v in baselines.items() if c != "nearest_neighbour" and not _better(metric, real[0], v[0])]
            status = ("uninformative" if real_lost else "warning" if lost else "unresolved" if unresolved else "ok")
            if real_lost:
                text = (f"{'does not beat ' + ', '.join(lost) if lost else 'beats every trivial baseline'}, but real vs "
                        f"real does not beat {', '.join(real_lost)} either: this metric does not separate real images "
                        f"from the baselines on this data")
            elif lost:
                text = f"does not beat {', '.join(lost)}"
            elif unresolved:
                text = (f"beats every trivial baseline, but not beyond the noise against {', '.join(unresolved)}"
                        + (" (the paired difference's 95% interval reaches 0)" if paired else " (the intervals overlap)"))
                undecidable = [c for c in unresolved if c in real_paired and real_paired[c][2] >= 0]
                if undecidable:  # real images themselves are not told from it at this n: more images, not a better G
                    text += (f"; real held-out images in its place do not beat {', '.join(undecidable)} beyond the "
                             f"noise either")
            else:
                text = "beats every trivial baseline" + (
                    " beyond the noise (each paired difference's 95% interval below 0)" if paired
                    else "" if math.isnan(generated[1]) else " beyond the intervals")
            if status in ("ok", "unresolved") and not math.isnan(position):
                text += f"; it sits {position:.2f} of the way from the best baseline (0) to real vs real (1)"
            result.append({"direction": direction, "family": family, "metric": metric, "view": view, "status": status,
                           "generated": generated[0], "generated_interval": [generated[1], generated[2]],
                           "real_heldout": real[0], "best_baseline": best_name, "best_baseline_value": best[0],
                           "position": position, "n": int(generated[3]), "n_real": int(real[3]),
                           "text": f"{direction.upper()} {family}: generated {generated[0]:.4g} {text} (best "
                                   f"{best_name} {best[0]:.4g}; real vs real {real[0]:.4g}; n = {int(generated[3])})"})
        mem = memorisation[(memorisation["direction"] == direction) & (memorisation["class"] == "(all)")]
        for view in sorted(set(mem["view"])):
            pair = mem[mem["view"] == view].set_index("candidate")
            if not {"generated", "real_heldout"} <= set(pair.index):
                continue
            gen, ref = pair.loc["generated"], pair.loc["real_heldout"]
            gen_ci, ref_ci = wilson_interval(gen["rate"], int(gen["n"])), wilson_interval(ref["rate"], int(ref["n"]))
            worse = gen_ci[0] > ref_ci[1]  # above real held-out beyond both 95% intervals (the report's reading)
            reading = ("above" if worse else "within noise of" if gen["rate"] > ref["rate"] else "not above")
            result.append({"direction": direction, "family": f"memorisation ({view})", "metric": "memorisation",
                           "view": view, "status": "warning" if worse else "ok", "generated": float(gen["rate"]),
                           "generated_interval": list(gen_ci), "real_heldout": float(ref["rate"]),
                           "real_heldout_interval": list(ref_ci), "n": int(gen["n"]), "n_real": int(ref["n"]),
                           "text": f"{direction.upper()} memorisation ({view}): {gen['rate']:.3f} "
                                   f"[{gen_ci[0]:.3f}, {gen_ci[1]:.3f}] of generated test images are closer to a "
                                   f"training image than any held-out real image is ({reading} the real held-out "
                                   f"rate {ref['rate']:.3f} [{ref_ci[0]:.3f}, {ref_ci[1]:.3f}], 95% Wilson; "
                                   f"n = {int(gen['n'])} generated, {int(ref['n'])} real)"
                                   + (ONE_GROUP_CAVEAT if worse and gen.get("train_groups", 2) == 1 else "")})
    return result


def load_encoders(classify_dir: Path | None, modality: str, notes: list[str]) -> dict:
    """The feature encoders of one target modality: ``classifier`` (the classify stage's encoder.pt,
    when it exists) and ``random`` (the fixed random CNN)."""
    encoders = {"random": dist.RandomEncoder()}
    path = None if classify_dir is None else classify_dir / modality / "encoder.pt"
    if path is not None and path.is_file():
        model, _ = load_classifier(path)
        encoders = {"classifier": dist.classifier_encoder(model), **encoders}
    else:
        notes.append(f"no real-only {modality} classifier ({path}): classifier-feature metrics left out")
    return encoders


def _greyscale(images: torch.Tensor) -> bool:
    """True when every image has three equal channels (greyscale data, e.g. a round optical sensor)."""
    return bool(len(images)) and bool((images[:, 0] == images[:, 1]).all() and (images[:, 1] == images[:, 2]).all())


def run_score(params: dict, pairs_dir: str | Path, generated_root: str | Path, out_dir: str | Path,
              classify_dir: str | Path | None = None) -> dict:
    """Score every direction under ``generated_root``; write ``scores`` (per image), ``by_class``,
    ``distribution``, ``memorisation``, ``diversity``, ``differences``, ``brightness``, ``fixed_pattern`` and ``following`` (parquet and CSV) and ``summary.json`` (with
    ``goals``: :func:`goal_metrics`) to ``out_dir``. Reads ``params["score"]``: ``batch_size``,
    ``max_per_class`` and ``fid_resamples``.

    A direction without generated test images (e.g. a one-modality dataset) is skipped with its
    reason in ``summary.json`` ``not_scored``; with no direction left the tables are empty.
    ``classify_dir`` holds the classify stage's outputs, whose real-only classifiers are the
    ``classifier`` feature view."""
    pairs_dir, generated_root = Path(pairs_dir), Path(generated_root)
    classify_dir = None if classify_dir is None else Path(classify_dir)
    seed = SCORE_SEED
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    settings = params["score"]
    tables, distributions, differences, memorised, diverse, bright, patterned, following = [], [], [], [], [], [], [], []
    nearest_pairs, strips = [], {}
    notes, not_scored, facts = [], {}, {}
    timings = {"ssim": 0.0, "distribution": 0.0, "memorisation and diversity": 0.0}
    tiles = TileReader()
    for direction in DIRECTIONS:
        generated = read_table(generated_root / direction / "generated.parquet", GENERATED_COLUMNS,
                               f"the {direction} output table of the generate stage")
        if (generated["split"] == "test").sum() == 0:
            not_scored[direction] = f"no generated test images in {generated_root / direction / 'generated.parquet'}"
            continue
        pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
        sets: dict = {}
        started = time.perf_counter()
        tables.append(score_direction(direction, generated, splits, pairs, settings["batch_size"], sets, tiles))
        timings["ssim"] += time.perf_counter() - started
        target = DIRECTIONS[direction][1]
        cache = FeatureCache(load_encoders(classify_dir, target, notes))
        started = time.perf_counter()
        table, facts[direction], paired = distribution_direction(direction, sets, cache, seed,
                                                                 settings["max_per_class"], settings["fid_resamples"])
        distributions.append(table)
        differences.append(paired)
        timings["distribution"] += time.perf_counter() - started
        started = time.perf_counter()
        memorised.append(memorisation_direction(direction, sets, cache))
        table, strips[direction] = nearest_training_direction(direction, sets, cache)
        nearest_pairs.append(table)
        diverse.append(diversity_direction(direction, sets, cache, seed))
        bright.append(brightness_direction(direction, sets))
        patterned.append(fixed_pattern_direction(direction, sets, seed))
        source = DIRECTIONS[direction][0]
        input_encoder = (load_encoders(classify_dir, source, []).get("classifier")
                         if "classifier" in cache.encoders else None)
        following.append(following_direction(direction, sets, seed, cache, input_encoder))
        timings["memorisation and diversity"] += time.perf_counter() - started
        facts[direction]["images_encoded"] = dict(cache.encoded)
        facts[direction]["greyscale"] = _greyscale(sets["real_test"][0])
        facts[direction]["ssim_name"] = "SSIM" if facts[direction]["greyscale"] else "Colour-SSIM"
    scores = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=SCORE_COLUMNS)
    classes_table = by_class(scores, seed) if tables else pd.DataFrame(columns=["direction", "scope", "candidate", "class"])
    distribution = pd.concat(distributions, ignore_index=True) if distributions else pd.DataFrame(columns=DISTRIBUTION_COLUMNS)
    memorisation = pd.concat(memorised, ignore_index=True) if memorised else pd.DataFrame(columns=MEMORISATION_COLUMNS)
    diversity = pd.concat(diverse, ignore_index=True) if diverse else pd.DataFrame(columns=DIVERSITY_COLUMNS)
    paired = pd.concat(differences, ignore_index=True) if differences else pd.DataFrame(columns=DIFFERENCE_COLUMNS)
    brightness = pd.concat(bright, ignore_index=True) if bright else pd.DataFrame(columns=BRIGHTNESS_COLUMNS)
    patterns = pd.concat(patterned, ignore_index=True) if patterned else pd.DataFrame(columns=FIXED_PATTERN_COLUMNS)
    follows = pd.concat(following, ignore_index=True) if following else pd.DataFrame(columns=FOLLOWING_COLUMNS)
    nearest = (pd.concat(nearest_pairs, ignore_index=True) if nearest_pairs
               else pd.DataFrame(columns=NEAREST_TRAINING_COLUMNS))
    generated_rows = scores.loc[scores["candidate"] == "generated", "image"]
    size = _image_side(generated_rows.iloc[0]) if len(generated_rows) else None
    found = (verdicts(distribution, memorisation, paired) + brightness_verdicts(brightness)
             + fixed_pattern_verdicts(patterns) + following_verdicts(follows)) if tables else []
    summary = {
        "synthetic": params["dataset"]["source"] == "synthetic",
        "image_size": size,
        "candidates": CANDIDATES,
        "aligned_pairs": {d: int(scores[(scores["direction"] == d) & (scores["candidate"] == "generated")]
                                 ["colour_ssim"].notna().sum()) for d in DIRECTIONS if d not in not_scored},
        "ms_ssim": MS_SSIM_NOTE.format(size=size),
        "scores": headline(classes_table) if tables else {},
        "distribution": facts,
        "verdicts": found,
        "goals": goal_metrics(distribution, memorisation, diversity, paired, follows),
        "not_scored": not_scored,
        "notes": notes,
        "seconds": {k: round(v, 2) for k, v in timings.items()},
    }
    with atomic_output_dir(out_dir) as tmp:
        for name, table in (("scores", scores), ("by_class", classes_table), ("distribution", distribution),
                            ("memorisation", memorisation), ("diversity", diversity), ("differences", paired),
                            ("brightness", brightness), ("fixed_pattern", patterns), ("following", follows),
                            ("nearest_training", nearest)):
            table.to_parquet(tmp / f"{name}.parquet", index=False)
            table.to_csv(tmp / f"{name}.csv", index=False, float_format="%.6f")
        for direction, strip in strips.items():
            if strip is not None:
                write_png(tmp / f"nearest_training_{direction}.png", strip)
        (tmp / "summary.json").write_text(json.dumps(_plain(summary), indent=2, allow_nan=False) + "\n")
    _print_summary(summary)
    return summary


def _print_summary(summary: dict) -> None:
    """The stage's console lines: set-to-set levels, verdicts, what was not scored, notes, diversity, seconds."""
    facts, found, timings = summary["distribution"], summary["verdicts"], summary["seconds"]
    not_scored, notes = summary["not_scored"], summary["notes"]
    for direction, levels in summary["scores"].items():
        name = facts[direction]["ssim_name"]
        parts = [f"{c} {v['set_colour_ssim']:.3f}" for c, v in levels.items() if v["set_colour_ssim"] is not None]
        print(f"score {direction}: set-to-set {name} " + ", ".join(parts))
    for item in found:
        print(f"  {'WARNING: ' if item['status'] == 'warning' else ''}{item['text']}")
    for direction, reason in not_scored.items():
        print(f"score {direction}: not scored: {reason}")
    for note in notes:
        print(f"  note: {note}")
    for direction, goals in summary["goals"].items():
        for view in ("pixels", "classifier"):
            if f"diversity_{view}" in goals:
                d = goals[f"diversity_{view}"]
                print(f"score {direction}: within-class diversity ratio ({view}) {d['value']:.3f} "
                      f"[{d['low']:.3f}, {d['high']:.3f}], median over {d['classes']} classes")
    print(f"score: {timings['ssim']:.1f} s SSIM, {timings['distribution']:.1f} s distribution metrics, "
          f"{timings['memorisation and diversity']:.1f} s memorisation check and diversity")


def _plain(value):
    """``value`` for strict JSON: numpy scalars as Python numbers, NaN and infinities as None."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value
