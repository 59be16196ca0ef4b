"""metrics.json: the run's headline numbers for ``dvc metrics``, plain numbers only.

SSIM levels and distribution metrics per direction (generated, real held-out, the best trivial
baseline), accuracy per classify modality, and counts; no timings, dates, versions or paths, so
identical inputs give identical numbers.
"""

from __future__ import annotations

import pandas as pd

from vtgen.core.confusion import realistic_gan_test
from vtgen.core.domain import DIRECTIONS, direction_producing
from vtgen.io.report_tables import DISTRIBUTION_BASELINES, has_value

REFERENCE_LEVELS = {"real_train": "real_vs_real", "nearest_neighbour": "nearest_neighbour",
                    "mean_image": "mean_image", "flat_mean_colour": "flat_mean_colour"}
# True when lower is better
LOWER_IS_BETTER = {"kid": True, "kid_classwise": True, "fid": True, "spectrum": True, "precision": False, "recall": False,
                   "density": False, "coverage": False}
# metrics.json: (metric, view) per direction, each with generated, real_heldout and best_baseline
HEADLINE_DISTRIBUTION = [("kid", "classifier"), ("kid_classwise", "classifier"), ("fid", "classifier"),
                         ("two_sample", "classifier"), ("spectrum", "pixels")]


def _number(value) -> float | None:
    """A finite value rounded to 6 decimals, or None."""
    return None if value is None or pd.isna(value) else round(float(value), 6)


def _compact(values: dict) -> dict:
    return {k: v for k, v in values.items() if v is not None and v != {}}



def ssim_headline(by_class: pd.DataFrame, direction: str) -> dict:
    """Colour-SSIM of the pooled model (scope 'all') and the reference levels over all classes; per-class
    models under ``scopes``; ``test_images`` counts the generated test images scored."""
    overall = by_class[(by_class["direction"] == direction) & (by_class["class"] == "(all)")]
    result: dict = {"scopes": {}}
    for row in overall.itertuples(index=False):
        if row.candidate == "generated":
            values = _compact({"set_colour_ssim": _number(row.set_colour_ssim),
                               "aligned_colour_ssim": _number(row.colour_ssim),
                               "nearest_real_colour_ssim": _number(row.nearest_real_colour_ssim),
                               "test_images": int(row.images)})
            (result if row.scope == "all" else result["scopes"].setdefault(row.scope, {})).update(values)
        elif row.candidate in REFERENCE_LEVELS:
            name = REFERENCE_LEVELS[row.candidate]
            result[name] = _number(row.set_colour_ssim)
            result[f"{name}_aligned"] = _number(row.colour_ssim)
    return _compact(result)


def best_baseline(metric: str, values: dict[str, float]) -> tuple[str, float] | None:
    """The best of the trivial baselines ``values`` for ``metric`` (two-sample accuracy: closest to 0.5)."""
    finite = {name: value for name, value in values.items() if has_value(value)}
    if not finite:
        return None
    if metric == "two_sample":
        return min(finite.items(), key=lambda item: abs(item[1] - 0.5))
    if LOWER_IS_BETTER.get(metric, True):
        return min(finite.items(), key=lambda item: item[1])
    return max(finite.items(), key=lambda item: item[1])


def distribution_headline(distribution: pd.DataFrame, memorisation: pd.DataFrame, direction: str) -> dict:
    """Per HEADLINE_DISTRIBUTION metric over all classes: generated (pooled model), real held-out and the
    best trivial baseline; and the memorisation rate (classifier features) of generated and real held-out."""
    rows = distribution[(distribution["direction"] == direction) & (distribution["class"] == "(all)")]
    result = {}
    for metric, view in HEADLINE_DISTRIBUTION:
        part = rows[(rows["metric"] == metric) & (rows["view"] == view)]
        values = {(c, s): v for c, s, v in zip(part["candidate"], part["scope"], part["value"])}
        generated = values.get(("generated", "all"),
                               next((v for (c, _), v in sorted(values.items()) if c == "generated"), None))
        best = best_baseline(metric, {c: values[(c, "-")] for c in DISTRIBUTION_BASELINES if (c, "-") in values})
        result[f"{metric}_{view}"] = _compact({"generated": _number(generated),
                                               "real_heldout": _number(values.get(("real_heldout", "-"))),
                                               "best_baseline": _number(best[1]) if best else None})
    mem = memorisation[(memorisation["direction"] == direction) & (memorisation["class"] == "(all)")
                       & (memorisation["view"] == "classifier")].set_index("candidate")["rate"]
    result["memorisation_classifier"] = _compact({c: _number(mem.get(c)) for c in ("generated", "real_heldout")})
    return _compact(result)


# the score stage's image checks: verdict metric -> metrics.json key
CHECK_KEYS = {"brightness": "brightness_outside", "fixed_pattern": "fixed_pattern_share",
              "following_pixels": "input_following_r_pixels", "following_classifier": "input_following_r_classifier"}


def checks_headline(score_summary: dict, direction: str) -> dict:
    """The score stage's image checks, generated beside real held-out: ``brightness_outside`` (the share of test
    images darker or lighter than every real training image of their class), ``fixed_pattern_share`` (the share
    of the images' fine detail drawn at the same place with the same sign in every image) and
    ``input_following_r_<view>`` (pixels, classifier: within a class, how far the outputs' distances follow their
    inputs', a Mantel r; its ``real_heldout``: the real targets of the same inputs, aligned data only); a key is
    left out where its verdict is missing."""
    found = {}
    for verdict in score_summary.get("verdicts") or []:
        key = CHECK_KEYS.get(verdict.get("metric"))
        if key and verdict.get("direction") == direction:
            found[key] = _compact({"generated": _number(verdict["generated"]),
                                   "real_heldout": _number(verdict.get("real_heldout"))})
    return found


def classify_headline(entry: dict) -> dict:
    """Mean final-epoch test accuracy over seeds per setting, the GAN-test with its 95% Wilson interval on its
    test images (``gan_test_interval``: low, high, images; the classify stage's), the GAN-test as a share of the
    real-only test accuracy (``gan_test_vs_real``: how recognisable generated images are against real
    ones), for a generator told the class the GAN-test of its outputs told the class read from each input
    (``gan_test_read``, the classify stage's), the test-set size, the accuracy gained from generated images per comparison
    (``gain_from_generated``) with its paired 95% interval (``gain_from_generated_paired95``: low, high) and the
    policy's (``policy``: the chosen setting's test accuracy beside real only's, their difference with its
    paired 95% interval (gain_low, gain_high) and 1 where it adds generated images, 0 where not)."""
    table, summary = entry["accuracy"], entry["summary"]
    if summary.get("status", "ok") != "ok" or table.empty:
        return {}
    last = table[table["epoch"] == table.groupby(["setting", "seed"])["epoch"].transform("max")]
    result = {s: _number(g["test_accuracy"].mean()) for s, g in last.groupby("setting")}
    gan = last.loc[(last["setting"] == "real"), "gan_test_accuracy"].dropna()
    result["gan_test"] = _number(gan.mean()) if len(gan) else None
    if result["gan_test"] is not None and result.get("real"):
        result["gan_test_vs_real"] = _number(result["gan_test"] / result["real"])
    judged = summary.get("gan_test") or {}
    if result["gan_test"] is not None and judged.get("interval"):
        result["gan_test_interval"] = {"low": _number(judged["interval"][0]), "high": _number(judged["interval"][1]),
                                       "images": judged.get("images")}
    result["gan_test_read"] = _number((summary.get("gan_test_read") or {}).get("final_mean"))
    result["seeds"] = int(last["seed"].nunique())
    result["real_test_images"] = (summary.get("counts") or {}).get("real_test")
    result["gain_from_generated"] = _compact({c["setting"]: _number(c["difference"])
                                              for c in summary.get("comparisons") or []})
    result["gain_from_generated_paired95"] = _compact({
        c["setting"]: {"low": _number(c["paired_interval"][0]), "high": _number(c["paired_interval"][1])}
        for c in summary.get("comparisons") or [] if c.get("paired_interval")})
    test = (summary.get("policy") or {}).get("test") or {}
    if test.get("accuracy") is not None:
        gain_low, gain_high = test.get("gain_interval") or (None, None)
        result["policy"] = _compact({"accuracy": _number(test["accuracy"]), "real_only": _number(test["real_accuracy"]),
                                     "gain": _number(test.get("gain")), "gain_low": _number(gain_low),
                                     "gain_high": _number(gain_high),
                                     "uses_generated": int(test["setting"] != "real")})
    return _compact(result)


def realistic_gan_tests(classify: dict, runs: list[dict]) -> dict:
    """Per target modality, the GAN-test real held-out images would get in place of its translations
    (:func:`vtgen.core.confusion.realistic_gan_test`, from both classify stages' ``real_confusion``):
    {modality: {"value", "told_class", "inputs"}}. ``told_class`` when every model of the producing direction
    was told each input's class (conditioning class or reference); otherwise the image of each input is of
    the class the input modality's real-only classifier reads from it, as for a generator told nothing.
    A modality is left out when either confusion is missing or their classes differ."""
    found = {}
    for source, target in DIRECTIONS.values():
        judge, reader = (classify.get(m, {}).get("summary") or {} for m in (target, source))
        if not judge.get("real_confusion") or not reader.get("real_confusion") or judge.get("classes") != reader.get("classes"):
            continue
        kinds = {r.get("conditioning", "none") for r in runs
                 if r.get("direction") == direction_producing(target) and r.get("status", "ok") == "ok"}
        told = bool(kinds) and kinds <= {"class", "reference"}
        value = realistic_gan_test(reader["real_confusion"], judge["real_confusion"], told)
        if value is not None:
            inputs = int(round(sum(map(sum, reader["real_confusion"]))))
            found[target] = {"value": _number(value), "told_class": told, "inputs": inputs}
    return found


def headline_metrics(data: dict) -> dict:
    """The numbers for ``dvc metrics``: SSIM levels and distribution metrics per direction, accuracy per
    modality (with ``gan_test_realistic`` beside the GAN-test where :func:`realistic_gan_tests` found it) and
    counts; no timings, dates, versions or paths."""
    goals = data["score_summary"].get("goals") or {}  # issue 24's numbers, each with its interval and n
    metrics = {d: _compact(ssim_headline(data["by_class"], d)
                           | distribution_headline(data["distribution"], data["memorisation"], d)
                           | checks_headline(data["score_summary"], d)
                           | {"goals": goals.get(d) or {}})
               for d in DIRECTIONS}
    metrics = _compact(metrics)
    accuracy = {m: classify_headline(e) for m, e in data["classify"].items()}
    for modality, oracle in (data.get("realistic_gan_test") or {}).items():
        if accuracy.get(modality, {}).get("gan_test") is not None:
            accuracy[modality]["gan_test_realistic"] = oracle["value"]
    metrics["classify"] = _compact(accuracy)
    ingest = data["ingest"]
    metrics["counts"] = _compact({"classes": len(ingest.get("classes", [])), "images_kept": ingest.get("kept"),
                                  "quarantined": ingest.get("quarantined"),
                                  "models": sum(1 for r in data["models"] if str(r.get("status", "ok")) == "ok")})
    return metrics
