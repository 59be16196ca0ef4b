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
``summary.json`` holds one verdict per direction and metric family.
"""

from __future__ import annotations

import json
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
from vtgen.core.metrics import bootstrap_interval, colour_ssim, grey_ssim, pairwise_colour_ssim, psnr
from vtgen.io.classifiers import load_classifier
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.io.tables import candidate_label, CANDIDATES

ALIGNED_METRICS = ["colour_ssim", "grey_ssim", "psnr", "ms_ssim"]
SET_METRICS = ["set_colour_ssim", "nearest_real_colour_ssim"]
SCORE_COLUMNS = ["direction", "scope", "candidate", "class", "image", "group", "ground_truth_path",
                 *ALIGNED_METRICS, *SET_METRICS, "nearest_real_path"]
INTERVAL_METRICS = ["colour_ssim", "grey_ssim", "psnr", "set_colour_ssim", "nearest_real_colour_ssim"]
DISTRIBUTION_COLUMNS = ["direction", "scope", "class", "candidate", "view", "metric", "value", "low", "high",
                        "n", "n_reference"]
MEMORISATION_COLUMNS = ["direction", "class", "view", "candidate", "rate", "nearest_is_train_share", "n", "n_train",
                        "train_groups"]
# a warning's reading where some class trained on one split group: copying and learning the class look alike there
ONE_GROUP_CAVEAT = ("; at least one class has a single training group (one instance or session), so a generator that "
                    "learns that class can only reproduce that group's look, and held-out real images come from "
                    "other groups: here the check cannot tell copying from learning the class")
BASELINES = ["nearest_neighbour", "mean_image", "flat_mean_colour", "blurred_real"]
# metric: (family shown in verdicts, True when lower is better, target value for "better" = closer to it)
DISTRIBUTION_METRICS = {"kid": ("KID", True), "fid": ("FID", True), "two_sample": ("two-sample accuracy", True),
                        "precision": ("precision", False), "recall": ("recall", False),
                        "density": ("density", False), "coverage": ("coverage", False),
                        "spectrum": ("power-spectrum distance", True)}
VERDICT_METRICS = [("kid", "classifier"), ("kid", "random"), ("fid", "classifier"), ("fid", "random"),
                   ("two_sample", "classifier"), ("coverage", "classifier"), ("spectrum", "pixels")]
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
                     names: list[str], groups: list[str], truth_paths: list[str],
                     real_test: dict[str, tuple[np.ndarray, list[str]]], size: int, batch_size: int) -> pd.DataFrame:
    """Score one candidate set of a direction: aligned where a ground truth is listed, and set-to-set
    and nearest-real against ``real_test`` ({class: (images N x S x S x 3, paths)}). ``groups`` are the
    test groups the images come from (the unit of the bootstrap intervals)."""
    table = pd.DataFrame({"direction": direction, "scope": scope, "candidate": candidate, "class": classes,
                          "image": names, "group": groups, "ground_truth_path": truth_paths})
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
                    batch_size: int, sets: dict | None = None) -> pd.DataFrame:
    """Per-image scores of one direction: every scope's generated test outputs and the reference candidates.
    When ``sets`` is a dict it receives the images scored, for the distribution metrics:
    ``{(candidate, scope): (uint8 images, classes, groups)}`` plus ``"real_test"`` and ``"real_train"``."""
    sets = {} if sets is None else sets
    target_modality = DIRECTIONS[direction][1]
    group_of = dict(zip(splits["path"], splits["group"]))
    test = generated[generated["split"] == "test"].sort_values(["scope", "class", "input_path"])
    if test.empty:
        raise ValueError(f"{direction}: generated.parquet lists no test-split outputs to score")
    size = _image_side(test["output_path"].iloc[0])
    real = splits[splits["modality"] == target_modality]
    real_test = {}
    test_rows = real[real["split"] == "test"].sort_values(["class", "path"])
    test_images = read_tiles(list(test_rows["path"]), size)
    sets["real_test"] = (test_images, test_rows["class"].to_numpy(), test_rows["group"].to_numpy())
    for name in sorted(set(test_rows["class"])):
        rows_of = (test_rows["class"] == name).to_numpy()
        real_test[name] = (_channels_last(test_images[torch.tensor(rows_of)]), list(test_rows["path"][rows_of]))
    tables = []
    for scope, rows in test.groupby("scope", sort=True):
        images, classes = read_tiles(list(rows["output_path"]), size), rows["class"].to_numpy()
        groups = [group_of.get(p, p) for p in rows["input_path"]]
        sets[("generated", scope)] = (images, classes, np.array(groups))
        tables.append(score_candidates(
            direction, scope, "generated", images, classes, list(rows["output_path"]), groups,
            list(rows["ground_truth_path"].fillna("")), real_test, size, batch_size))

    inputs = test.drop_duplicates("input_path")
    train_pairs = pairs[pairs["split"] == "train"].sort_values("input_path")
    references = reference_candidates(
        read_tiles(list(inputs["input_path"]), size), inputs["class"].to_numpy(),
        read_tiles(list(train_pairs["input_path"]), size), read_tiles(list(train_pairs["target_path"]), size),
        train_pairs["class"].to_numpy())
    input_groups = [group_of.get(p, p) for p in inputs["input_path"]]
    for candidate, images in references.items():
        names = [f"{candidate}:{p}" for p in inputs["input_path"]]
        sets[(candidate, "-")] = (images, inputs["class"].to_numpy(), np.array(input_groups))
        tables.append(score_candidates(direction, "-", candidate, images, inputs["class"].to_numpy(), names,
                                       input_groups, list(inputs["ground_truth_path"].fillna("")), real_test, size,
                                       batch_size))

    real_train = real[(real["split"] == "train") & real["class"].isin(set(inputs["class"]))].sort_values("path")
    train_images = read_tiles(list(real_train["path"]), size)
    sets["real_train"] = (train_images, real_train["class"].to_numpy(), real_train["group"].to_numpy())
    tables.append(score_candidates(
        direction, "-", "real_train", train_images, real_train["class"].to_numpy(),
        list(real_train["path"]), list(real_train["group"]), [""] * len(real_train), real_test, size, batch_size))
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


def _set_metrics(reference: dict, candidate: dict) -> dict[tuple[str, str], tuple[float, float, float]]:
    """{(view, metric): (value, low, high)} of one candidate set against the reference set; ``reference`` and
    ``candidate`` map a view name to features (``pixels`` to uint8 images). A metric that cannot be
    computed for these sets (too few images) is NaN."""
    out = {}

    def record(view, metric, compute):
        try:
            out[(view, metric)] = compute()
        except ValueError:
            out[(view, metric)] = (math.nan, math.nan, math.nan)

    for view in [v for v in reference if v != "pixels"]:
        real, fake = reference[view], candidate[view]

        def kid_value():
            # subsets of half the smaller set, so that the subsets differ and their spread means something
            smaller = min(len(real), len(fake))
            mean, std = dist.kid(real, fake, subsets=KID_SUBSETS, subset_size=max(2, smaller // 2) if smaller >= 4 else smaller)
            return mean, mean - 1.96 * std, mean + 1.96 * std

        record(view, "kid", kid_value)
        record(view, "fid", lambda: (dist.fid(real, fake), math.nan, math.nan))

        def two_sample():
            if min(len(real), len(fake)) < TWO_SAMPLE_MIN_IMAGES:
                raise ValueError("too few images for a two-sample test")
            result = dist.two_sample_test(real, fake)
            return result.accuracy, result.low, result.high

        record(view, "two_sample", two_sample)
        try:
            scores = dist.prdc_scores(real, fake)
        except ValueError:
            scores = {}
        for metric in ("precision", "recall", "density", "coverage"):
            value = scores.get(metric, math.nan)
            out[(view, metric)] = (value, math.nan, math.nan)
    record("pixels", "spectrum", lambda: (dist.spectrum_distance(reference["pixels"], candidate["pixels"]),
                                          math.nan, math.nan))
    return out


def _features(encoder, images: torch.Tensor) -> torch.Tensor:
    """``dist.image_features`` of ``images``, each distinct image encoded once (the flat and mean
    baselines repeat one image per class)."""
    unique, inverse = torch.unique(images.flatten(1), dim=0, return_inverse=True)
    if len(unique) == len(images):
        return dist.image_features(encoder, images)
    return dist.image_features(encoder, unique.reshape(-1, *images.shape[1:]))[inverse]


def encode_sets(sets: dict, encoders: dict) -> dict:
    """Features of every image set of a direction, computed once: {key: {view: features}} for the keys
    of ``sets`` (candidates, ``real_test``, ``real_train``); the ``pixels`` view holds the images.
    The training images serve only the memorisation check, which uses the classifier view and pixels."""
    encoded = {}
    for key, (images, *_) in sets.items():
        views = {v: e for v, e in encoders.items() if key != "real_train" or v != "random"}
        encoded[key] = {"pixels": images, **{view: _features(e, images) for view, e in views.items()}}
    return encoded


def distribution_direction(direction: str, sets: dict, encoded: dict, encoders: dict,
                           seed: int) -> tuple[pd.DataFrame, dict]:
    """Distribution metrics of every candidate set of one direction against real held-out half B, per
    class and over all classes (``(all)``); see the module docstring. ``encoded`` holds the sets'
    features (:func:`encode_sets`). Returns the table (DISTRIBUTION_COLUMNS) and facts for
    summary.json (halving, blur sigma)."""
    test_images, test_classes, test_groups = sets["real_test"]
    in_a, by_group = heldout_halves(test_classes, test_groups, seed)
    sigma = dist.default_blur_sigma(test_images.shape[-1])
    half_a = torch.from_numpy(in_a)
    blurred = dist.gaussian_blur(test_images[half_a], sigma)
    features = {("real_heldout", "-"): {v: f[half_a] for v, f in encoded["real_test"].items()},
                ("blurred_real", "-"): {"pixels": blurred,
                                        **{v: dist.image_features(e, blurred) for v, e in encoders.items()}}}
    classes_of = {("real_heldout", "-"): test_classes[in_a], ("blurred_real", "-"): test_classes[in_a]}
    for key, value in sets.items():
        if isinstance(key, tuple):
            features[key], classes_of[key] = encoded[key], value[1]
    reference = {v: f[~half_a] for v, f in encoded["real_test"].items()}
    reference_classes = test_classes[~in_a]
    rows = []
    for name in [*sorted(set(test_classes)), "(all)"]:
        ref_rows = np.ones(len(reference_classes), bool) if name == "(all)" else reference_classes == name
        limit = int(in_a.sum()) if name == "(all)" else int((test_classes[in_a] == name).sum())
        ref = {view: values[torch.from_numpy(ref_rows)] for view, values in reference.items()}
        for (candidate, scope), classes in classes_of.items():
            rows_of = np.ones(len(classes), bool) if name == "(all)" else classes == name
            chosen = np.flatnonzero(rows_of)
            chosen = chosen[_subsample(len(chosen), limit, np.random.default_rng([seed, len(rows)]))]
            if len(chosen) == 0:
                continue
            index = torch.from_numpy(chosen)
            fake = {view: values[index] for view, values in features[(candidate, scope)].items()}
            for (view, metric), (value, low, high) in _set_metrics(ref, fake).items():
                rows.append({"direction": direction, "scope": scope, "class": name, "candidate": candidate,
                             "view": view, "metric": metric, "value": value, "low": low, "high": high,
                             "n": len(chosen), "n_reference": int(ref_rows.sum())})
    facts = {"halves_by": "group" if by_group else "image (some class has a single test group)",
             "blur_sigma": sigma, "half_a": int(in_a.sum()), "half_b": int((~in_a).sum())}
    return pd.DataFrame(rows, columns=DISTRIBUTION_COLUMNS), facts


def memorisation_direction(direction: str, sets: dict, encoded: dict) -> pd.DataFrame:
    """Memorisation of the pooled model's generated test images (MEMORISATION_COLUMNS): per class and
    over all, in each encoder's features and in pixels, beside the same rates for real held-out images.
    ``train_groups``: distinct training split groups (instances, sessions) of the class; for ``(all)``
    the fewest of any class."""
    key = ("generated", "all") if ("generated", "all") in sets else next(
        k for k in sets if isinstance(k, tuple) and k[0] == "generated")
    gen_classes, train_classes, held_classes = sets[key][1], sets["real_train"][1], sets["real_test"][1]
    groups = pd.Series(sets["real_train"][2]).groupby(pd.Series(train_classes)).nunique()
    train_groups = {**groups.to_dict(), "(all)": int(groups.min()) if len(groups) else 0}
    rows = []
    for view in encoded["real_train"]:
        g, t, h = (encoded[k][view] for k in (key, "real_train", "real_test"))
        if view == "pixels":
            g, t, h = (x.flatten(1).double() for x in (g, t, h))
        for name in [*sorted(set(gen_classes)), "(all)"]:
            pick = (lambda c: np.ones(len(c), bool)) if name == "(all)" else (lambda c: c == name)
            gi, ti, hi = (torch.from_numpy(pick(c)) for c in (gen_classes, train_classes, held_classes))
            try:
                result = dist.memorisation(g[gi], t[ti], h[hi])
            except ValueError:
                continue
            rows.append({"direction": direction, "class": name, "view": view, "candidate": "generated",
                         "rate": result.rate, "nearest_is_train_share": result.nearest_is_train_share,
                         "n": int(gi.sum()), "n_train": int(ti.sum()), "train_groups": train_groups.get(name, 0)})
            rows.append({"direction": direction, "class": name, "view": view, "candidate": "real_heldout",
                         "rate": result.reference_rate,
                         "nearest_is_train_share": result.nearest_is_train_reference,
                         "n": int(hi.sum()), "n_train": int(ti.sum()), "train_groups": train_groups.get(name, 0)})
    return pd.DataFrame(rows, columns=MEMORISATION_COLUMNS)


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


def verdicts(table: pd.DataFrame, memorisation: pd.DataFrame) -> list[dict]:
    """One verdict per direction and metric family (VERDICT_METRICS, memorisation) for the pooled
    model over all classes: does generated beat every trivial baseline (beyond the intervals where
    the metric has one), and where does it sit between the best baseline (0) and real vs real (1)?
    Status: ``ok``, ``unresolved`` (better, but an interval overlaps), ``warning`` (a baseline is as
    good or better), or ``uninformative`` (real vs real itself does not beat the mean image, flat
    colour or blurred real, so the metric cannot rank on this data; the nearest-neighbour targets
    are real images, which a distribution metric places near real vs real by construction)."""
    result = []
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
            unresolved = [c for c, v in baselines.items() if c not in lost
                          and _separated(generated[1:3], v[1:3]) is False]
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
                text = f"beats every trivial baseline, but its interval overlaps {', '.join(unresolved)}'s"
            else:
                text = "beats every trivial baseline" + ("" if math.isnan(generated[1]) else " beyond the intervals")
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
            worse = gen["rate"] > ref["rate"]
            result.append({"direction": direction, "family": f"memorisation ({view})", "metric": "memorisation",
                           "view": view, "status": "warning" if worse else "ok", "generated": float(gen["rate"]),
                           "real_heldout": float(ref["rate"]), "n": int(gen["n"]), "n_real": int(ref["n"]),
                           "text": f"{direction.upper()} memorisation ({view}): {gen['rate']:.3f} of generated test "
                                   f"images are closer to a training image than any held-out real image is "
                                   f"({'above' if worse else 'not above'} the real held-out rate {ref['rate']:.3f}; "
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
    ``distribution`` and ``memorisation`` (parquet and CSV) and ``summary.json`` to ``out_dir``.

    A direction without generated test images (e.g. a one-modality dataset) is skipped with its
    reason in ``summary.json`` ``not_scored``; with no direction left the tables are empty.
    ``classify_dir`` holds the classify stage's outputs, whose real-only classifiers are the
    ``classifier`` feature view."""
    pairs_dir, generated_root = Path(pairs_dir), Path(generated_root)
    classify_dir = None if classify_dir is None else Path(classify_dir)
    seed = SCORE_SEED
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    tables, distributions, memorised, notes, not_scored, facts = [], [], [], [], {}, {}
    timings = {"ssim": 0.0, "distribution": 0.0, "memorisation": 0.0}
    for direction in DIRECTIONS:
        generated = read_table(generated_root / direction / "generated.parquet", GENERATED_COLUMNS,
                               f"the {direction} output table of the generate stage")
        if (generated["split"] == "test").sum() == 0:
            not_scored[direction] = f"no generated test images in {generated_root / direction / 'generated.parquet'}"
            continue
        pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
        sets: dict = {}
        started = time.perf_counter()
        tables.append(score_direction(direction, generated, splits, pairs, params["score"]["batch_size"], sets))
        timings["ssim"] += time.perf_counter() - started
        target = DIRECTIONS[direction][1]
        encoders = load_encoders(classify_dir, target, notes)
        started = time.perf_counter()
        encoded = encode_sets(sets, encoders)
        table, facts[direction] = distribution_direction(direction, sets, encoded, encoders, seed)
        distributions.append(table)
        timings["distribution"] += time.perf_counter() - started
        started = time.perf_counter()
        memorised.append(memorisation_direction(direction, sets, encoded))
        timings["memorisation"] += time.perf_counter() - started
        facts[direction]["greyscale"] = _greyscale(sets["real_test"][0])
        facts[direction]["ssim_name"] = "SSIM" if facts[direction]["greyscale"] else "Colour-SSIM"
    scores = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=SCORE_COLUMNS)
    classes_table = by_class(scores, seed) if tables else pd.DataFrame(columns=["direction", "scope", "candidate", "class"])
    distribution = pd.concat(distributions, ignore_index=True) if distributions else pd.DataFrame(columns=DISTRIBUTION_COLUMNS)
    memorisation = pd.concat(memorised, ignore_index=True) if memorised else pd.DataFrame(columns=MEMORISATION_COLUMNS)
    generated_rows = scores.loc[scores["candidate"] == "generated", "image"]
    size = _image_side(generated_rows.iloc[0]) if len(generated_rows) else None
    found = verdicts(distribution, memorisation) if tables else []
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
        "not_scored": not_scored,
        "notes": notes,
        "seconds": {k: round(v, 2) for k, v in timings.items()},
    }
    with atomic_output_dir(out_dir) as tmp:
        for name, table in (("scores", scores), ("by_class", classes_table), ("distribution", distribution),
                            ("memorisation", memorisation)):
            table.to_parquet(tmp / f"{name}.parquet", index=False)
            table.to_csv(tmp / f"{name}.csv", index=False, float_format="%.6f")
        (tmp / "summary.json").write_text(json.dumps(_plain(summary), indent=2, allow_nan=False) + "\n")
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
    print(f"score: {timings['ssim']:.1f} s SSIM, {timings['distribution']:.1f} s distribution metrics, "
          f"{timings['memorisation']:.1f} s memorisation check")
    return summary


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
