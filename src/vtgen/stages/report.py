"""Report stage: one self-contained page that says what this run did and what it found.

``run_report`` reads only the folders named on its command line (ingest, pairs, models, generated,
scores, classify), collects every number the page shows into one dictionary (:func:`collect`) and
writes into ``out_dir``:

* ``index.html`` and ``summary.md``: rendered from the Jinja2 templates ``report.html`` / ``report.md``
  in ``vtgen/io/templates`` (HTML autoescaped), figures beside them in ``figures/``;
* ``metrics.json``: the headline numbers only (:func:`headline_metrics`), plain numbers with sorted
  keys, so identical inputs give a byte-identical file for ``dvc metrics diff``;
* ``timings.json``: wall seconds of each input's job, from the ``timing.json`` each stage command
  writes into its own output folder;
* ``plots/training.csv``: every model's dvclive losses in long format (step, model, losses).

The page opens with the verdicts: one line per direction and metric family (the score stage's
``verdicts``; WARNING where generated data does not beat a trivial baseline), the classification
comparisons, and a plain line for every direction that was not scored and why. Then: data provenance
(synthetic or real, counts, duplicates, pair kinds per direction and split, dropped pairs, per-class
test n), the parameters and code version, the distribution metrics and the memorisation check per
direction, the paper's Table I (V2T), Table II (T2V) and Table III (classification per iteration)
with this run's numbers, their n and 95% intervals (comparisons whose intervals overlap are called
"within noise", never ranked), the paper's printed values (``vtgen/io/paper.yaml``) row for row
where the experiment matches, image grids, training-loss curves and stage timings.
"""

from __future__ import annotations

import datetime as dt
import errno
import os
import platform
import shutil
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import yaml  # noqa: E402

from vtgen.core.domain import direction_producing, DIRECTIONS, MODALITIES  # noqa: E402
from vtgen.io.provenance import code_version  # noqa: E402
from vtgen.io.report_pages import (PAPER, PAPER_ROWS, interval_cell, overlap, plain, read_json, render_page,  # noqa: E402
                                   table_view, write_json)
from vtgen.io.tables import PAIR_KINDS, QUARANTINE_COLUMNS, candidate_label, read_table  # noqa: E402

SETTING_ORDER = ["real", "real+generated", "low-data real", "low-data real+generated"]
REFERENCE_LEVELS = {"real_train": "real_vs_real", "nearest_neighbour": "nearest_neighbour",
                    "mean_image": "mean_image", "flat_mean_colour": "flat_mean_colour"}
BY_CLASS_KEYS = ["direction", "scope", "candidate", "class"]
BY_CLASS_NEEDS = [*BY_CLASS_KEYS, "colour_ssim", "grey_ssim", "psnr", "ms_ssim", "set_colour_ssim",
                  "nearest_real_colour_ssim", "images"]
ACCURACY_NEEDS = ["modality", "setting", "seed", "epoch", "test_accuracy", "gan_test_accuracy"]
CLASSIFY_BY_CLASS_NEEDS = ["modality", "setting", "class", "images", "accuracy", "low", "high", "seeds"]
DISTRIBUTION_NEEDS = ["direction", "scope", "class", "candidate", "view", "metric", "value", "low", "high", "n",
                      "n_reference"]
MEMORISATION_NEEDS = ["direction", "class", "view", "candidate", "rate", "nearest_is_train_share", "n", "n_train"]
PAIR_NEEDS = ["direction", "split", "class", "aligned"]
GAN_TEST = "GAN-test"
SSIM_BASELINES = ("nearest_neighbour", "mean_image", "flat_mean_colour")
DISTRIBUTION_BASELINES = ("nearest_neighbour", "mean_image", "flat_mean_colour", "blurred_real")
# (metric, view) columns of the distribution tables, in order; label; True when lower is better
DISTRIBUTION_SHOWN = [("kid", "classifier"), ("fid", "classifier"), ("two_sample", "classifier"),
                      ("precision", "classifier"), ("recall", "classifier"), ("coverage", "classifier"),
                      ("kid", "random"), ("fid", "random"), ("two_sample", "random"), ("spectrum", "pixels")]
METRIC_LABELS = {"kid": "KID", "fid": "FID", "two_sample": "two-sample acc.", "precision": "precision",
                 "recall": "recall", "density": "density", "coverage": "coverage", "spectrum": "spectrum dist."}
LOWER_IS_BETTER = {"kid": True, "fid": True, "spectrum": True, "precision": False, "recall": False,
                   "density": False, "coverage": False}
# metrics.json: (metric, view) per direction, each with generated, real_heldout and best_baseline
HEADLINE_DISTRIBUTION = [("kid", "classifier"), ("fid", "classifier"), ("two_sample", "classifier"),
                         ("spectrum", "pixels")]
TRAINING_COLUMNS = ["step", "model", "loss_d", "loss_g_gan", "loss_g_l1"]
FIGURES = ("losses", "scores", "grid_v2t", "grid_t2v", "classification", "timings")


@dataclass(frozen=True)
class ReportInputs:
    """The stage folders the report reads, and nothing else."""

    ingest: Path
    pairs: Path
    models: Path
    generated: Path
    scores: Path
    classify: Path


# ---------------------------------------------------------------- reading the run


def model_runs(models_dir: Path) -> list[dict]:
    """train.json of every model under ``models_dir/<direction>/<scope>/``, in direction then scope order."""
    runs = [read_json(path) | {"folder": path.parent} for path in models_dir.glob("*/*/train.json")]
    if not runs:
        raise FileNotFoundError(errno.ENOENT, "no trained model (<direction>/<scope>/train.json) in", str(models_dir))
    order = list(DIRECTIONS)
    return sorted(runs, key=lambda r: (order.index(r["direction"]) if r["direction"] in order else 9, r["scope"]))


def training_curves(runs: list[dict]) -> pd.DataFrame:
    """Long table of every model's dvclive losses: step, model ("v2t/all"), loss_*, val_* (NaN where not logged)."""
    tables = []
    for run in runs:
        metrics = run["folder"] / "dvclive" / "plots" / "metrics"
        series = [(tsv.stem, tsv) for tsv in sorted(metrics.glob("train/loss_*.tsv"))]
        series += [(f"val_{tsv.stem}", tsv) for tsv in sorted(metrics.glob("val/*.tsv"))]
        merged = None
        for column, tsv in series:
            table = pd.read_csv(tsv, sep="\t").iloc[:, :2]
            table.columns = ["step", column]
            merged = table if merged is None else merged.merge(table, on="step", how="outer")
        if merged is not None:
            tables.append(merged.assign(model=f"{run['direction']}/{run['scope']}"))
    long = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=TRAINING_COLUMNS)
    extra = sorted(c for c in long.columns if c not in TRAINING_COLUMNS)
    return long.reindex(columns=TRAINING_COLUMNS + extra).sort_values(["model", "step"], ignore_index=True)


def classification(classify_dir: Path) -> dict:
    """Per modality: its classify summary.json, accuracy table and the settings marked ``at_chance``."""
    found = {}
    for modality in MODALITIES:
        folder = classify_dir / modality
        summary = read_json(folder / "summary.json")
        accuracy = read_table(folder / "accuracy.parquet", ACCURACY_NEEDS, f"the classify stage's {modality} table")
        final = _optional_columns(folder / "by_class.parquet", ["modality", "setting", "class"], CLASSIFY_BY_CLASS_NEEDS,
                                  f"the classify stage's {modality} per-class table")
        found[modality] = {"summary": summary, "accuracy": accuracy, "by_class": final,
                           "at_chance": at_chance(summary, accuracy)}
    return found


def settings_in(names) -> list[str]:
    """The settings among ``names`` in SETTING_ORDER, then any other (the policy's candidates) sorted."""
    present = set(names)
    return [s for s in SETTING_ORDER if s in present] + sorted(present - set(SETTING_ORDER) - {GAN_TEST})


def _optional_columns(path: Path, keys: list[str], needs: list[str], what: str) -> pd.DataFrame:
    """A stage table that may be empty with its key columns only (a stage with nothing to do); when it
    has rows, every column of ``needs`` must be there."""
    table = read_table(path, keys, what)
    return read_table(path, needs, what) if len(table) else table.reindex(columns=needs)


def _split_order(split: str) -> tuple:
    order = ("train", "val", "test")
    return (order.index(split) if split in order else 9, split)


def pair_kinds(pairs_dir: Path) -> dict:
    """{direction: {split: {kind: pairs}}} from the pair tables (kinds pixel, name, class; tables without a
    ``pair_kind`` column count aligned pairs as pixel and the rest as class)."""
    found = {}
    for direction in DIRECTIONS:
        table = read_table(pairs_dir / f"{direction}.parquet", PAIR_NEEDS, f"the pairs stage's {direction} table")
        kind = table["pair_kind"] if "pair_kind" in table else np.where(table["aligned"], "pixel", "class")
        counts = table.assign(kind=kind).groupby(["split", "kind"]).size()
        found[direction] = {split: {k: int(counts[(split, k)]) for k in PAIR_KINDS if (split, k) in counts.index}
                            for split in sorted(set(table["split"]), key=_split_order)}
    return found


def at_chance(summary: dict, accuracy: pd.DataFrame) -> list[str]:
    """Settings the classify stage marked as ending at chance level: in summary.json (the mean over seeds), or
    in the accuracy table at a seed's final epoch (an earlier epoch at chance is how training starts, not
    how it ends); none when unmarked."""
    flagged = {name for name, entry in (summary.get("settings") or {}).items()
               if isinstance(entry, dict) and entry.get("at_chance") is True}
    if "at_chance" in accuracy.columns and not accuracy.empty:
        final = accuracy[accuracy["epoch"] == accuracy.groupby(["setting", "seed"])["epoch"].transform("max")]
        flagged |= set(final.loc[final["at_chance"].fillna(False).astype(bool), "setting"])
    return sorted(flagged, key=lambda s: (SETTING_ORDER.index(s) if s in SETTING_ORDER else 9, s))


def stage_timings(inputs: ReportInputs, runs: list[dict]) -> pd.DataFrame:
    """Wall seconds of the job behind each input folder (its ``timing.json``), in pipeline order; jobs
    without one (a stage run outside the ``vtgen`` command) are left out."""
    jobs = [("ingest", inputs.ingest), ("pairs", inputs.pairs)]
    jobs += [(f"train_{r['direction']}_{r['scope']}", r["folder"]) for r in runs]
    jobs += [(f"generate_{d}", inputs.generated / d) for d in DIRECTIONS] + [("score", inputs.scores)]
    jobs += [(f"classify_{m}", inputs.classify / m) for m in MODALITIES]
    rows = []
    for job, folder in jobs:
        if (folder / "timing.json").is_file():
            record = read_json(folder / "timing.json")
            rows.append({"job": job, "stage": record.get("stage", job.split("_")[0]),
                         "seconds": float(record["seconds"]), "finished": record.get("finished", "")})
    return pd.DataFrame(rows, columns=["job", "stage", "seconds", "finished"])


def run_facts(params: dict) -> dict:
    """Code version, build time and machine of this report (shown on the page, never in metrics.json)."""
    try:
        torch_version = metadata.version("torch")
    except metadata.PackageNotFoundError:
        torch_version = "not installed"
    return {"code_version": code_version(), "built": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
            "python": platform.python_version(), "torch": torch_version, "cpus": os.cpu_count(),
            "preset": params["translation"]["preset"], "scope": list(params["translation"]["scope"])}


def collect(params: dict, inputs: ReportInputs) -> dict:
    """Every number and table the report shows, read from the input folders only."""
    runs = model_runs(inputs.models)
    synthetic = params["dataset"]["source"] == "synthetic"
    return {
        "title": "vtgen report" + (" (SYNTHETIC data)" if synthetic else ""), "synthetic": synthetic,
        "dataset": {"source": params["dataset"]["source"], "path": str(params["dataset"]["path"])},
        "ingest": read_json(inputs.ingest / "summary.json"),
        "quarantine": read_table(inputs.ingest / "quarantine.parquet", QUARANTINE_COLUMNS,
                                 "the ingest stage's quarantine table"),
        "pairs": read_json(inputs.pairs / "summary.json"),
        "run": run_facts(params), "params_yaml": yaml.safe_dump(params, sort_keys=False),
        "models": runs, "training": training_curves(runs),
        "pair_kinds": pair_kinds(inputs.pairs),
        "score_summary": read_json(inputs.scores / "summary.json"),
        "by_class": _optional_columns(inputs.scores / "by_class.parquet", BY_CLASS_KEYS, BY_CLASS_NEEDS,
                                      "the score stage's by_class table"),
        "distribution": read_table(inputs.scores / "distribution.parquet", DISTRIBUTION_NEEDS,
                                   "the score stage's distribution table"),
        "memorisation": read_table(inputs.scores / "memorisation.parquet", MEMORISATION_NEEDS,
                                   "the score stage's memorisation table"),
        "classify": classification(inputs.classify), "timings": stage_timings(inputs, runs),
    }


# ---------------------------------------------------------------- verdicts


def translation_reason(summary: dict, direction: str) -> str | None:
    """The reason a stage summary (pairs or ingest) records in its ``translation`` entry, overall or per
    direction, for ``direction`` having no translation, or None when it records none."""
    entry = summary.get("translation")
    if isinstance(entry, dict) and isinstance(entry.get(direction), (dict, str)):
        entry = entry[direction]
    if isinstance(entry, dict):
        return entry.get("reason") or None
    return entry or None if isinstance(entry, str) else None


def not_scored(data: dict) -> dict[str, str]:
    """{direction: why it has no scores} for the directions without scores (a one-modality dataset:
    the pairs stage's reason first, then the ingest stage's, the train stage's status, the score stage's)."""
    recorded = data["score_summary"].get("not_scored") or {}
    scored = set(data["by_class"]["direction"])
    result = {}
    for direction in DIRECTIONS:
        if direction in scored and direction not in recorded:
            continue
        statuses = [str(r["status"]).removeprefix("not applicable: ") for r in data["models"]
                    if r["direction"] == direction and str(r.get("status", "ok")).startswith("not applicable")]
        result[direction] = (translation_reason(data["pairs"], direction) or translation_reason(data["ingest"], direction)
                             or (statuses[0] if statuses else None)
                             or recorded.get(direction) or "the score stage has no scores for this direction")
    return result


VERDICT_MARKS = {"warning": "WARNING: ", "unresolved": "", "ok": "", "not scored": ""}


def verdict_lines(data: dict) -> list[dict]:
    """The lines the report opens with: ``{"status", "line"}`` per direction and metric family (the
    score stage's verdicts), per classification comparison, and per direction or modality not scored."""
    found, skipped, lines = data["score_summary"].get("verdicts") or [], not_scored(data), []

    def add(status: str, text: str) -> None:
        lines.append({"status": status, "line": VERDICT_MARKS.get(status, "") + text})

    for direction in DIRECTIONS:
        if direction in skipped:
            add("not scored", f"{direction.upper()}: not scored: {skipped[direction]}")
            continue
        mine = [v for v in found if v.get("direction") == direction]
        if not mine:
            add("unresolved", f"{direction.upper()}: no verdict (the score stage's summary.json has none for it)")
        for verdict in mine:
            add(verdict.get("status", "ok"), verdict["text"])
    for modality, entry in data["classify"].items():
        summary = entry["summary"]
        if summary.get("status", "ok") != "ok":
            add("not scored", f"{modality} classification: {summary['status']}")
            continue
        n = (summary.get("counts") or {}).get("real_test", "?")
        for item in summary.get("comparisons") or []:
            add("unresolved" if item.get("overlap") else "ok",
                f"{modality} classification, {item['setting']} against {item['against']}: accuracy "
                f"{item['difference']:+.3f}, {item['verdict']} (n = {n} test images)")
        for setting in entry["at_chance"]:
            add("warning", f"{modality} classification: '{setting}' ends at chance level; its accuracies say nothing "
                           f"about the generated data")
    return lines


# ---------------------------------------------------------------- the first screen


VERDICT_COLOURS = ("ok", "unresolved", "warning", "uninformative", "not scored")


def policy_rows(data: dict) -> list[dict]:
    """"Does generated data help here?": per modality, the classify stage's policy (the setting chosen on the
    validation split, or real only and why) and its test accuracy beside real only's, with intervals."""
    rows = []
    for modality, entry in data["classify"].items():
        summary = entry["summary"]
        policy = summary.get("policy")
        if summary.get("status", "ok") != "ok" or not policy:
            rows.append({"modality": modality, "answer": "not measured", "status": "not scored",
                         "chosen": "—", "accuracy": "—", "real": "—", "gain": "—", "n": "—",
                         "why": summary.get("status") if summary.get("status", "ok") != "ok"
                         else "this classify run predates the policy (no summary.json policy)"})
            continue
        test = policy["test"]
        gain = test.get("gain")
        low, high = test.get("gain_interval") or (None, None)
        if not policy["uses_generated"]:
            answer, status = (("no: real only", "unresolved") if policy.get("candidates")
                              else ("not tested: real only", "not scored"))
        else:
            answer = "yes" if low is not None and low > 0 else "chosen on validation; within noise on test"
            status = "ok" if low is not None and low > 0 else "unresolved"
        if gain is not None and high is not None and high < 0:
            status = "warning"  # below real only beyond the interval: the guarantee failed here
        rows.append({"modality": modality, "answer": answer, "status": status, "chosen": policy["chosen"],
                     "accuracy": interval_cell(test.get("accuracy"), *(test.get("interval") or (None, None))),
                     "real": interval_cell(test.get("real_accuracy"), *(test.get("real_interval") or (None, None))),
                     "gain": "—" if gain is None else f"{gain:+.3f}" + (f" [{low:+.3f}, {high:+.3f}]"
                                                                         if low is not None else ""),
                     "n": test.get("images", "—"), "why": policy.get("reason", "")})
    return rows


def verdict_grid(data: dict) -> dict | None:
    """The score stage's verdicts as one direction x family grid: ``{"families", "rows": [{"direction",
    "cells": [{"status", "text"}]}]}``, each cell the status (VERDICT_COLOURS) and a short value; None
    when there are no verdicts."""
    found = data["score_summary"].get("verdicts") or []
    if not found:
        return None
    families = list(dict.fromkeys(v["family"] for v in found if v.get("family")))
    rows = []
    for direction in sorted({v["direction"] for v in found}, key=lambda d: list(DIRECTIONS).index(d)
                            if d in DIRECTIONS else 9):
        mine = {v["family"]: v for v in found if v.get("direction") == direction}
        cells = []
        for family in families:
            v = mine.get(family)
            if v is None:
                cells.append({"status": "not scored", "text": "—"})
                continue
            value = v.get("generated")
            text = v.get("status", "ok") + ("" if value is None else f" ({value:.3g})")
            cells.append({"status": v.get("status", "ok"), "text": text})
        rows.append({"direction": direction.upper(), "cells": cells})
    return {"families": families, "rows": rows}


# ---------------------------------------------------------------- headline numbers (metrics.json)


def _number(value) -> float | None:
    """A finite value rounded to 6 decimals, or None."""
    return None if value is None or pd.isna(value) else round(float(value), 6)


def _compact(values: dict) -> dict:
    return {k: v for k, v in values.items() if v is not None and v != {}}


def _finite(value) -> bool:
    return value is not None and not pd.isna(value)


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
    finite = {name: value for name, value in values.items() if _finite(value)}
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


def classify_headline(entry: dict) -> dict:
    """Mean final-epoch test accuracy over seeds per setting, the GAN-test, the GAN-test as a share of the
    real-only test accuracy (``gan_test_vs_real``: how recognisable generated images are against real
    ones), the test-set size, the accuracy gained from generated images per comparison
    (``gain_from_generated``) and the policy's (``policy``: the chosen setting's test accuracy beside
    real only's, their difference and 1 where it adds generated images, 0 where not)."""
    table, summary = entry["accuracy"], entry["summary"]
    if summary.get("status", "ok") != "ok" or table.empty:
        return {}
    last = table[table["epoch"] == table.groupby(["setting", "seed"])["epoch"].transform("max")]
    result = {s: _number(g["test_accuracy"].mean()) for s, g in last.groupby("setting")}
    gan = last.loc[(last["setting"] == "real"), "gan_test_accuracy"].dropna()
    result["gan_test"] = _number(gan.mean()) if len(gan) else None
    if result["gan_test"] is not None and result.get("real"):
        result["gan_test_vs_real"] = _number(result["gan_test"] / result["real"])
    result["seeds"] = int(last["seed"].nunique())
    result["real_test_images"] = (summary.get("counts") or {}).get("real_test")
    result["gain_from_generated"] = _compact({c["setting"]: _number(c["difference"])
                                              for c in summary.get("comparisons") or []})
    test = (summary.get("policy") or {}).get("test") or {}
    if test.get("accuracy") is not None:
        result["policy"] = _compact({"accuracy": _number(test["accuracy"]), "real_only": _number(test["real_accuracy"]),
                                     "gain": _number(test.get("gain")),
                                     "uses_generated": int(test["setting"] != "real")})
    return _compact(result)


def headline_metrics(data: dict) -> dict:
    """The numbers for ``dvc metrics``: SSIM levels and distribution metrics per direction, accuracy per
    modality and counts; no timings, dates, versions or paths."""
    goals = data["score_summary"].get("goals") or {}  # issue 24's numbers, each with its interval and n
    metrics = {d: _compact(ssim_headline(data["by_class"], d)
                           | distribution_headline(data["distribution"], data["memorisation"], d)
                           | {"goals": goals.get(d) or {}})
               for d in DIRECTIONS}
    metrics = _compact(metrics)
    metrics["classify"] = _compact({m: classify_headline(e) for m, e in data["classify"].items()})
    ingest = data["ingest"]
    metrics["counts"] = _compact({"classes": len(ingest.get("classes", [])), "images_kept": ingest.get("kept"),
                                  "quarantined": ingest.get("quarantined"),
                                  "models": sum(1 for r in data["models"] if str(r.get("status", "ok")) == "ok")})
    return metrics


# ---------------------------------------------------------------- tables


def ssim_name(summary: dict, direction: str) -> str:
    """"SSIM" for greyscale data (the score stage's ``ssim_name``), else "Colour-SSIM"."""
    return ((summary.get("distribution") or {}).get(direction) or {}).get("ssim_name", "Colour-SSIM")


def _records(rows: pd.DataFrame) -> dict:
    return {(r["candidate"], r["scope"], r["class"]): r for r in rows.to_dict("records")}


def _cell(record: dict | None, metric: str, digits: int = 3) -> str:
    """A by_class mean with its 95% interval, or an em dash."""
    if record is None:
        return "—"
    return interval_cell(record.get(metric), record.get(f"{metric}_low"), record.get(f"{metric}_high"), digits)


def _against(record: dict | None, references: dict[str, dict], metric: str, label: str = "") -> str:
    """Generated against the best of ``references`` (higher is better): above or below only when the 95%
    intervals do not overlap, otherwise "within noise"."""
    references = {c: r for c, r in references.items() if r is not None and _finite(r.get(metric))}
    if record is None or not references or not _finite(record.get(metric)):
        return "—"
    name, best = max(references.items(), key=lambda item: item[1][metric])
    name = label or name.replace("_", " ")
    same = overlap((record.get(f"{metric}_low"), record.get(f"{metric}_high")),
                   (best.get(f"{metric}_low"), best.get(f"{metric}_high")))
    if same:
        return f"within noise of {name} (intervals overlap)"
    word = "above" if record[metric] > best[metric] else "below"
    return f"{word} {name}" + (" (no interval)" if same is None else "")


def ssim_tables(by_class: pd.DataFrame, direction: str, name: str = "Colour-SSIM"
                ) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """The paper-shaped tables of one direction: set-to-set SSIM (the paper's protocol) and, when the data
    has ground truth, the aligned scores; one row per class plus ``(all)``; every score with its 95%
    interval, n per row and generated against the best trivial baseline ("within noise" when the
    intervals overlap)."""
    rows = by_class[by_class["direction"] == direction]
    classes = sorted(c for c in rows["class"].unique() if c != "(all)") + ["(all)"]
    scopes = sorted(rows.loc[rows["candidate"] == "generated", "scope"].unique(), key=lambda s: (s != "all", s))
    found = _records(rows)

    def get(candidate: str, cls: str, scope: str = "-") -> dict | None:
        return found.get((candidate, scope, cls))

    def suffix(scope: str) -> str:
        return "" if len(scopes) == 1 else f" [{scope}]"

    def n(record: dict | None) -> int | str:
        return "—" if record is None else int(record["images"])

    set_table = pd.DataFrame({"class": classes})
    for scope in scopes:
        generated = [get("generated", c, scope) for c in classes]
        set_table[f"n{suffix(scope)}"] = [n(r) for r in generated]
        set_table[f"generated{suffix(scope)}"] = [_cell(r, "set_colour_ssim") for r in generated]
        set_table[f"generated, nearest real{suffix(scope)}"] = [_cell(r, "nearest_real_colour_ssim") for r in generated]
        set_table[f"generated vs best baseline{suffix(scope)}"] = [
            _against(r, {b: get(b, c) for b in SSIM_BASELINES}, "set_colour_ssim") for r, c in zip(generated, classes)]
    set_table["n real"] = [n(get("real_train", c)) for c in classes]
    set_table["real vs real"] = [_cell(get("real_train", c), "set_colour_ssim") for c in classes]
    for candidate in SSIM_BASELINES:
        set_table[candidate.replace("_", " ")] = [_cell(get(candidate, c), "set_colour_ssim") for c in classes]
    if rows.loc[rows["candidate"] == "generated", "colour_ssim"].notna().sum() == 0:
        return set_table, None
    aligned = pd.DataFrame({"class": classes})
    metrics = [("colour_ssim", name, 3), ("grey_ssim", "grey SSIM", 3), ("psnr", "PSNR dB", 2), ("ms_ssim", "MS-SSIM", 3)]
    for scope in scopes:
        generated = [get("generated", c, scope) for c in classes]
        aligned[f"n{suffix(scope)}"] = [n(r) for r in generated]
        for metric, label, digits in metrics:
            if metric == "grey_ssim" and name == "SSIM":
                continue  # greyscale data: the same number as the SSIM column
            if metric != "ms_ssim" or any(r is not None and _finite(r.get(metric)) for r in generated):
                aligned[f"{label}{suffix(scope)}"] = [_cell(r, metric, digits) for r in generated]
        aligned[f"vs best baseline{suffix(scope)}"] = [
            _against(r, {b: get(b, c) for b in SSIM_BASELINES}, "colour_ssim") for r, c in zip(generated, classes)]
    for candidate in SSIM_BASELINES:
        aligned[f"{candidate.replace('_', ' ')} {name}"] = [_cell(get(candidate, c), "colour_ssim") for c in classes]
    return set_table, aligned


STUDY_RUNS = {"cloth_types": "cloth_types", "network_parameters": "larger_batch, no_l1, more_iterations, more_images, "
              "double_resolution", "roi_with_noise": "roi_noise", "roi_no_noise": "roi_noise", "paired_dataset": "round_trip"}


def paper_matches(params: dict, by_class: pd.DataFrame, direction: str) -> dict[str, tuple[dict, str]]:
    """{paper row: (this run's set-to-set record, what matches)} for the rows of the paper's Table I/II
    that this run's models reproduce: ``cloth_types`` by per-class models, the ROI rows by the pooled model
    when the tactile frames were cut to a region (``roi.tactile_box`` not ``full``), with or without noise."""
    rows = by_class[(by_class["direction"] == direction) & (by_class["candidate"] == "generated")]
    overall = {r["scope"]: r for r in rows[rows["class"] == "(all)"].to_dict("records")}
    found = {}
    per_class = [r for scope, r in overall.items() if scope not in ("all", "-") and _finite(r.get("set_colour_ssim"))]
    if per_class:
        images = sum(int(r["images"]) for r in per_class)
        mean = sum(r["set_colour_ssim"] * int(r["images"]) for r in per_class) / images
        found["cloth_types"] = ({"set_colour_ssim": mean, "images": images},
                                f"{len(per_class)} per-class models, mean over their images (no pooled interval)")
    preset = (params.get("presets") or {}).get((params.get("translation") or {}).get("preset"), {}) or {}
    if direction == "v2t" and "all" in overall and (params.get("roi") or {}).get("tactile_box", "full") != "full":
        row = "roi_with_noise" if preset.get("noise") else "roi_no_noise"
        found[row] = (overall["all"], f"pooled model on the tactile ROI, noise {'on' if preset.get('noise') else 'off'}")
    return found


def paper_table(params: dict, by_class: pd.DataFrame, direction: str, name: str) -> pd.DataFrame:
    """The paper's Table I (V2T) or II (T2V) row for row, with this run's set-to-set score, n and 95%
    interval where this run's experiment matches the row."""
    matches = paper_matches(params, by_class, direction)
    rows = []
    for key, value in PAPER["colour_ssim"][direction].items():
        record, what = matches.get(key, (None, f"not run by the main job (studies: {STUDY_RUNS[key]})"))
        rows.append({"paper row": PAPER_ROWS[key], "paper Colour-SSIM": f"{value:.5f}",
                     f"this run, set-to-set {name}": _cell(record, "set_colour_ssim"),
                     "n": "—" if record is None else int(record["images"]), "experiment": what})
    return pd.DataFrame(rows)


def _wilson(rate: float, count: int) -> tuple[float, float]:
    from vtgen.core.classifier import wilson_interval  # torch: imported only when a table needs it

    return wilson_interval(rate, count)


def _mean_std_cells(values: pd.DataFrame, column: str, epochs, count: int | None) -> list[str]:
    stats = values.groupby("epoch")[column].agg(["mean", "std"])
    cells = []
    for epoch in epochs:
        if epoch not in stats.index:
            cells.append("")
            continue
        mean = stats.loc[epoch, "mean"]
        text = f"{mean:.3f} ± {np.nan_to_num(stats.loc[epoch, 'std']):.3f}"
        if count:
            low, high = _wilson(mean, count)
            text += f" [{low:.3f}, {high:.3f}]"
        cells.append(text)
    return cells


def accuracy_table(accuracy: pd.DataFrame, modality: str, test_images: int | None = None,
                   gan_images: int | None = None) -> pd.DataFrame:
    """Table III shape: test accuracy after each epoch (mean ± std over seeds, and the 95% Wilson interval
    of the mean on ``test_images``) per setting and the GAN-test (on ``gan_images``), beside the paper's
    value at the same iteration."""
    part = accuracy[accuracy["modality"] == modality]
    paper = PAPER["accuracy"].get(modality, {})
    iterations = sorted(set(part["epoch"]) | {i for values in paper.values() for i in values})
    table = pd.DataFrame({"epoch / iteration": iterations})
    for setting in settings_in(part["setting"]):
        table[setting] = _mean_std_cells(part[part["setting"] == setting], "test_accuracy", iterations, test_images)
    gan = part[(part["setting"] == "real") & part["gan_test_accuracy"].notna()]
    if not gan.empty:
        table["GAN-test (real-only classifier on generated)"] = _mean_std_cells(gan, "gan_test_accuracy",
                                                                                iterations, gan_images)
    for setting, values in paper.items():
        table[f"paper {setting}"] = [f"{values[i]:.4f}" if i in values else "" for i in iterations]
    return table


def final_accuracy_table(final: pd.DataFrame) -> pd.DataFrame:
    """Final-epoch accuracy per class and setting (mean over seeds) with its 95% Wilson interval and n."""
    classes = sorted(c for c in final["class"].unique() if c != "(all)") + ["(all)"]
    found = {(r["setting"], r["class"]): r for r in final.to_dict("records")}
    settings = settings_in(final["setting"])
    table = pd.DataFrame({"class": classes})
    table["n real test"] = [found[(settings[0], c)]["images"] if settings and (settings[0], c) in found else "—"
                            for c in classes]
    for setting in settings + ([GAN_TEST] if GAN_TEST in set(final["setting"]) else []):
        if setting == GAN_TEST:
            table["n generated test"] = [found[(setting, c)]["images"] if (setting, c) in found else "—" for c in classes]
        table[setting] = [interval_cell(found[(setting, c)]["accuracy"], found[(setting, c)]["low"],
                                        found[(setting, c)]["high"]) if (setting, c) in found else "—" for c in classes]
    return table


def comparison_table(summary: dict) -> pd.DataFrame | None:
    """With against without generated images: both final accuracies with 95% intervals, the difference
    and the classify stage's verdict ("within noise" when the intervals overlap)."""
    settings, n = summary.get("settings") or {}, (summary.get("counts") or {}).get("real_test", "—")
    rows = []
    for item in summary.get("comparisons") or []:
        a, b = settings.get(item["setting"], {}), settings.get(item["against"], {})
        rows.append({"setting": item["setting"],
                     "accuracy [95%]": interval_cell(a.get("final_mean"), *(a.get("interval") or (None, None))),
                     "against": item["against"],
                     "against: accuracy [95%]": interval_cell(b.get("final_mean"), *(b.get("interval") or (None, None))),
                     "difference": f"{item['difference']:+.3f}", "n test": n, "verdict": item["verdict"]})
    return pd.DataFrame(rows) if rows else None


METRIC_DIGITS = {"kid": 4, "fid": 2, "spectrum": 4}


def _candidate_order(candidate: str, scope: str) -> tuple:
    order = ["generated", "real_heldout", *DISTRIBUTION_BASELINES]
    return (order.index(candidate) if candidate in order else 9, scope != "all", candidate, scope)


def distribution_table(distribution: pd.DataFrame, direction: str, classes=("(all)",)) -> pd.DataFrame | None:
    """Rows: candidates (generated first, then real held-out, then the baselines), per class in ``classes``;
    columns: n, n of the reference half and each DISTRIBUTION_SHOWN metric (value [95% interval] where
    the metric has one)."""
    rows = distribution[(distribution["direction"] == direction) & distribution["class"].isin(classes)]
    if rows.empty:
        return None
    shown = [(m, v) for m, v in DISTRIBUTION_SHOWN if ((rows["metric"] == m) & (rows["view"] == v)).any()]
    out = []
    for cls in classes:
        part = rows[rows["class"] == cls]
        keys = sorted({(c, s) for c, s in zip(part["candidate"], part["scope"])}, key=lambda k: _candidate_order(*k))
        for candidate, scope in keys:
            mine = part[(part["candidate"] == candidate) & (part["scope"] == scope)]
            record = {"class": cls} if len(classes) > 1 else {}
            record |= {"candidate": candidate_label(candidate, scope).replace("_", " "), "n": int(mine["n"].max()),
                       "n ref": int(mine["n_reference"].max())}
            for metric, view in shown:
                value = mine[(mine["metric"] == metric) & (mine["view"] == view)]
                record[f"{METRIC_LABELS[metric]} ({view})"] = "—" if value.empty else interval_cell(
                    value["value"].iloc[0], value["low"].iloc[0], value["high"].iloc[0], METRIC_DIGITS.get(metric, 3))
            out.append(record)
    return pd.DataFrame(out)


def memorisation_table(memorisation: pd.DataFrame, direction: str) -> pd.DataFrame | None:
    """Per feature view over all classes: the share of generated and of real held-out test images closer to
    a training image than to any held-out image, each with n and a 95% Wilson interval; generated is read
    as above or below real only when the intervals do not overlap."""
    part = memorisation[(memorisation["direction"] == direction) & (memorisation["class"] == "(all)")]
    rows = []
    for view in sorted(set(part["view"]), key=lambda v: (["classifier", "random", "pixels"] + [v]).index(v)):
        pair = part[part["view"] == view].set_index("candidate")
        if not {"generated", "real_heldout"} <= set(pair.index):
            continue
        gen, real = pair.loc["generated"], pair.loc["real_heldout"]
        gen_interval, real_interval = _wilson(gen["rate"], int(gen["n"])), _wilson(real["rate"], int(real["n"]))
        same = overlap(gen_interval, real_interval)
        reading = ("within noise of real held-out (intervals overlap)" if same
                   else "above real held-out" if gen["rate"] > real["rate"] else "below real held-out")
        rows.append({"view": view, "generated rate [95%]": interval_cell(gen["rate"], *gen_interval),
                     "n generated": int(gen["n"]), "real held-out rate [95%]": interval_cell(real["rate"], *real_interval),
                     "n real": int(real["n"]), "n train": int(gen["n_train"]), "reading": reading})
    return pd.DataFrame(rows) if rows else None


def models_table(runs: list[dict]) -> pd.DataFrame:
    """One row per model folder from its train.json (a direction without pairs: its status, no model)."""
    return pd.DataFrame([{
        "model": f"{r['direction']}/{r['scope']}", "status": r.get("status", "ok"), "preset": r.get("preset"),
        "conditioning": r.get("conditioning", "none") if r.get("status", "ok") == "ok" else None,
        "objective": (r.get("objective") or {}).get("name"), "objective chosen because": (r.get("objective") or {}).get("reason"),
        "capacity": (r.get("capacity") or {}).get("mode"), "width (ngf)": (r.get("settings") or {}).get("ngf"),
        "size": (r.get("settings") or {}).get("size"), "iterations": r.get("steps"), "wall s": r.get("wall_seconds"),
        "s/iteration": r.get("seconds_per_iteration"), "final val L1": r.get("final_val_l1"),
        "device": r.get("device"), "precision": r.get("precision"), "precision chosen because": r.get("precision_reason"),
    } for r in runs])


def capacity_table(runs: list[dict]) -> pd.DataFrame | None:
    """Per model trained with capacity auto and per class: the width it needed, the step it settled at, and the
    model's compute against the fixed large model (train.json ``capacity``); None when no model used auto."""
    rows = []
    for r in runs:
        cap = r.get("capacity") or {}
        if cap.get("mode") != "auto":
            continue
        compute = cap["compute"]
        for name, choice in sorted(cap["per_class"].items()):
            rows.append({"model": f"{r['direction']}/{r['scope']}", "class": name,
                         "width needed": choice["width_needed"],
                         "settled at step": choice["settled_at_step"] if choice["settled_at_step"] is not None
                         else f"not settled by {cap['steps']}",
                         "model width": cap["chosen_width"], "model steps": cap["steps"],
                         "GFLOP (fixed large)": f"{compute['gflop']:.0f} ({compute['fixed_large_gflop']:.0f})",
                         "compute saved": f"{100 * compute['saved_share']:.0f}%",
                         "s (fixed large, estimated)": f"{compute['seconds']:.0f} ({compute['fixed_large_seconds_estimate']:.0f})"})
    return pd.DataFrame(rows) if rows else None


def capacity_view(runs: list[dict]) -> dict | None:
    """:func:`capacity_table` as template data, or None when no model used capacity auto."""
    table = capacity_table(runs)
    return None if table is None else table_view(
        table, "Capacity auto: per class, the smallest width within tolerance of the largest at the width probe, "
               "and the step its validation Colour-SSIM settled at; compute against the fixed large model")


# ---------------------------------------------------------------- figures


def _save_figure(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def loss_figure(training: pd.DataFrame, models: list[str], path: Path, max_models: int = 6) -> None:
    """Adversarial losses and L1 error (train, validation) per iteration, one row of panels per model
    (the first ``max_models`` of ``models`` that logged losses)."""
    models = [m for m in models if m in set(training["model"])][:max_models]
    fig, axes = plt.subplots(len(models), 2, figsize=(10, 2.6 * len(models)), squeeze=False)
    for (ax_gan, ax_l1), model in zip(axes, models):
        curves = training[training["model"] == model]
        for ax, names in ((ax_gan, ("loss_d", "loss_g_gan")), (ax_l1, ("loss_g_l1", "val_l1"))):
            for name in [n for n in names if n in curves and curves[n].notna().any()]:
                points = curves[curves[name].notna()]
                ax.plot(points["step"], points[name], label=name, marker="o" if name.startswith("val") else None)
            ax.set_xlabel("iteration")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
        ax_gan.set_title(f"{model}: adversarial losses")
        ax_l1.set_title(f"{model}: L1 error (train, validation)")
    _save_figure(fig, path)


def scores_figure(by_class: pd.DataFrame, path: Path, names: dict[str, str]) -> None:
    """Set-to-set and aligned SSIM (``names[direction]``) of every candidate over all classes, one panel per
    scored direction."""
    overall = by_class[by_class["class"] == "(all)"]
    directions = [d for d in DIRECTIONS if d in set(overall["direction"])]
    fig, axes = plt.subplots(1, len(directions), figsize=(11, 3.6), squeeze=False)
    for ax, direction in zip(axes[0], directions):
        part = overall[overall["direction"] == direction]
        labels = [candidate_label(c, s).replace("_", " ") for c, s in zip(part["candidate"], part["scope"])]
        y = np.arange(len(part))
        ax.barh(y - 0.2, part["set_colour_ssim"], height=0.4, label="set-to-set (paper protocol)")
        ax.barh(y + 0.2, part["colour_ssim"].fillna(0), height=0.4, label="aligned (own ground truth)")
        ax.set_yticks(y, labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel(names[direction])
        ax.set_title(direction.upper())
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="lower right")
    _save_figure(fig, path)


def accuracy_figure(accuracy: pd.DataFrame, path: Path) -> None:
    """Test accuracy per epoch per setting (mean, band min to max over seeds) and the GAN-test."""
    modalities = [m for m in MODALITIES if m in set(accuracy["modality"])]
    fig, axes = plt.subplots(1, max(len(modalities), 1), figsize=(11, 3.8), squeeze=False)
    for ax, modality in zip(axes[0], modalities):
        part = accuracy[accuracy["modality"] == modality]
        for setting in settings_in(part["setting"]):
            stats = part[part["setting"] == setting].groupby("epoch")["test_accuracy"].agg(["mean", "min", "max"])
            ax.plot(stats.index, stats["mean"], marker="o", markersize=3, label=setting)
            ax.fill_between(stats.index, stats["min"], stats["max"], alpha=0.15)
        gan = part[(part["setting"] == "real") & part["gan_test_accuracy"].notna()]
        if not gan.empty:
            stats = gan.groupby("epoch")["gan_test_accuracy"].mean()
            ax.plot(stats.index, stats.values, "k--", label="GAN-test")
        ax.set_title(f"{modality}: test accuracy (band: min to max over seeds)")
        ax.set_xlabel("iteration (epoch)")
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    _save_figure(fig, path)


def timing_figure(timings: pd.DataFrame, path: Path) -> None:
    """Wall seconds per job, one bar each."""
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(timings) + 1.2))
    ax.barh(timings["job"], timings["seconds"])
    ax.invert_yaxis()
    ax.set_xlabel("wall seconds (last run of each job)")
    ax.grid(axis="x", alpha=0.3)
    _save_figure(fig, path)


def write_figures(data: dict, generated_dir: Path, figures: Path) -> dict[str, bool]:
    """Draw (or copy) every figure the data allows into ``figures``; return which of FIGURES exist."""
    if data["training"]["step"].notna().any():
        loss_figure(data["training"], [f"{r['direction']}/{r['scope']}" for r in data["models"]],
                    figures / "losses.png")
    if not data["by_class"].empty:
        scores_figure(data["by_class"], figures / "scores.png", {d: ssim_name(data["score_summary"], d) for d in DIRECTIONS})
    for direction in DIRECTIONS:  # the generate stage's sheet: inputs | generated | ground truth per class
        if (generated_dir / direction / "preview.png").is_file():
            shutil.copyfile(generated_dir / direction / "preview.png", figures / f"grid_{direction}.png")
    tables = [e["accuracy"] for e in data["classify"].values() if not e["accuracy"].empty]
    if tables:
        accuracy_figure(pd.concat(tables, ignore_index=True), figures / "classification.png")
    if not data["timings"].empty:
        timing_figure(data["timings"], figures / "timings.png")
    return {name: (figures / f"{name}.png").is_file() for name in FIGURES}


# ---------------------------------------------------------------- the page


def conditioned_gan_test_note(modality: str, summary: dict, runs: list[dict]) -> str | None:
    """A caveat for the GAN-test of ``modality`` when the generator that made its images was told each
    image's class (train.json ``conditioning`` other than none): such images can be easier to classify
    than real ones, so the GAN-test is read against the real-only test accuracy; None otherwise."""
    kinds = sorted({r.get("conditioning", "none") for r in runs
                    if r.get("direction") == direction_producing(modality) and r.get("status", "ok") == "ok"} - {"none"})
    gan, real = summary.get("gan_test") or {}, (summary.get("settings") or {}).get("real") or {}
    if not kinds or gan.get("final_mean") is None or real.get("final_mean") is None:
        return None
    return (f"the generator of these images was told each image's class (conditioning {', '.join(kinds)}), so the "
            f"GAN-test ({gan['final_mean']:.3f}) shows in part that it follows the class it is given; read it against "
            f"the real-only test accuracy ({real['final_mean']:.3f}), not as realism alone")


def _classify_view(modality: str, entry: dict, runs: list[dict]) -> dict:
    summary, table = entry["summary"], entry["accuracy"]
    status = summary.get("status", "ok")
    tables = []
    if status == "ok" and not table.empty:
        n = (summary.get("counts") or {}).get("real_test")
        gan_n = (summary.get("gan_test") or {}).get("images")
        if not entry["by_class"].empty:
            tables.append(table_view(final_accuracy_table(entry["by_class"]),
                                     f"Final accuracy ({modality}) per class: mean over seeds [95% Wilson interval on "
                                     f"the n test images of the row]"))
        comparisons = comparison_table(summary)
        if comparisons is not None:
            tables.append(table_view(comparisons, f"With against without generated images ({modality}): ranked only "
                                                  f"when the 95% intervals do not overlap"))
        seeds = sorted(plain(s) for s in table["seed"].unique())
        tables.append(table_view(accuracy_table(table, modality, n, gan_n),
                                 f"Table III ({modality}): test accuracy after each iteration, mean ± std over seeds "
                                 f"{seeds} [95% Wilson interval on n = {n if n else '?'} real test images"
                                 + (f", {gan_n} generated for the GAN-test" if gan_n else "")
                                 + "], beside the paper's values at the same iteration"))
    caveat = conditioned_gan_test_note(modality, summary, runs) if status == "ok" else None
    return {"modality": modality, "status": status, "tables": tables, "at_chance": entry["at_chance"],
            "classes": len(summary.get("classes", [])), "notes": summary.get("notes", []) + ([caveat] if caveat else [])}


def _direction_view(data: dict, params: dict, number: str, direction: str) -> dict:
    """Everything the page shows for one scored direction: SSIM tables, the paper's rows, distribution
    metrics (all classes and per class) and the memorisation check."""
    by_class, distribution = data["by_class"], data["distribution"]
    name = ssim_name(data["score_summary"], direction)
    title = "visual to tactile (seeing to feel)" if direction == "v2t" else "tactile to visual (touching to see)"
    set_table, aligned = ssim_tables(by_class, direction, name)
    classes = sorted(c for c in distribution.loc[distribution["direction"] == direction, "class"].unique() if c != "(all)")
    overall, per_class = distribution_table(distribution, direction), distribution_table(distribution, direction, classes)
    memorised = memorisation_table(data["memorisation"], direction)
    return {
        "direction": direction, "name": name,
        "facts": (data["score_summary"].get("distribution") or {}).get(direction) or {},
        "set": table_view(set_table, f"Table {number}: {direction.upper()}, {title}: set-to-set {name} per class "
                                     f"[95% bootstrap interval over test groups]"),
        "aligned": None if aligned is None else table_view(
            aligned, f"Table {number}b: {direction.upper()}: aligned scores against each output's own ground truth "
                     f"[95% bootstrap interval over test groups]"),
        "paper": table_view(paper_table(params, by_class, direction, name),
                            f"Paper Table {number} ({direction.upper()}) row for row, beside this run where the "
                            f"experiment matches"),
        "distribution": None if overall is None else table_view(
            overall, f"{direction.upper()}: distribution metrics against real held-out half B, all classes"),
        "distribution_by_class": None if per_class is None or not classes else table_view(
            per_class, f"{direction.upper()}: distribution metrics per class"),
        "memorisation": None if memorised is None else table_view(
            memorised, f"{direction.upper()}: memorisation check, all classes"),
    }


def duplicate_counts(ingest: dict) -> dict:
    """The ingest stage's duplicate counts ({what: n}; its ``duplicates`` entry, numbers only)."""
    found = ingest.get("duplicates")
    if isinstance(found, dict):
        return {k.replace("_", " "): v for k, v in found.items()
                if isinstance(v, (int, float)) and not isinstance(v, bool)}
    return {k.removesuffix("_duplicates"): v for k, v in ingest.items()
            if k.endswith("_duplicates") and isinstance(v, (int, float)) and not isinstance(v, bool)}


def modalities_present(ingest: dict) -> list[str]:
    """The modalities the ingest stage kept (its ``modalities``, else the keys of ``per_class_modality``)."""
    if isinstance(ingest.get("modalities"), (list, dict)):
        return sorted(ingest["modalities"])
    return sorted({key.rsplit("/", 1)[-1] for key in ingest.get("per_class_modality") or {}})


def page_context(data: dict, figures: dict[str, bool], params: dict | None = None) -> dict:
    """What the report templates render: ``data`` with its tables as template data."""
    params = params or {}
    quarantine, timings, by_class = data["quarantine"], data["timings"], data["by_class"]
    ms_ssim = data["score_summary"].get("ms_ssim", "computed")
    skipped = not_scored(data)
    return {
        **{k: data[k] for k in ("title", "synthetic", "dataset", "ingest", "pairs", "run", "params_yaml")},
        "directions": list(DIRECTIONS), "figures": figures, "verdicts": verdict_lines(data),
        "policy": policy_rows(data), "verdict_grid": verdict_grid(data),
        "not_scored": skipped, "pair_kinds": data["pair_kinds"], "duplicates": duplicate_counts(data["ingest"]),
        "modalities": modalities_present(data["ingest"]),
        "test_per_class": {m: e["summary"].get("test_images_per_class") for m, e in data["classify"].items()
                           if e["summary"].get("test_images_per_class")},
        "quarantine": table_view(quarantine.head(30), f"Quarantined inputs ({len(quarantine)}; first 30 shown)")
        if not quarantine.empty else None,
        "models": table_view(models_table(data["models"]), "Trained generators (train.json)"),
        "capacity": capacity_view(data["models"]),
        "ms_ssim_note": None if ms_ssim == "computed" or not len(by_class) else f"MS-SSIM {ms_ssim}.",
        "ssim": [_direction_view(data, params, n, d) for n, d in (("I", "v2t"), ("II", "t2v"))
                 if d in set(by_class["direction"]) and d not in skipped],
        "classify": [_classify_view(m, e, data["models"]) for m, e in data["classify"].items()],
        "timings": table_view(timings[["job", "seconds", "finished"]],
                              "Wall time of each job (timing.json in its output folder)") if not timings.empty else None,
    }


def timings_record(timings: pd.DataFrame) -> dict:
    """timings.json: the jobs in pipeline order and their total wall seconds."""
    jobs = [{k: plain(v) for k, v in row.items()} for row in timings.to_dict("records")]
    return {"jobs": jobs, "total_seconds": round(float(timings["seconds"].sum()), 2)}


def run_report(params: dict, ingest_dir, pairs_dir, models_dir, generated_dir, scores_dir, classify_dir,
               out_dir: str | Path = "reports") -> dict:
    """Build index.html, summary.md, metrics.json, timings.json, plots/training.csv and figures/ in
    ``out_dir`` from the named stage folders only; return the headline metrics."""
    inputs = ReportInputs(*(Path(p) for p in (ingest_dir, pairs_dir, models_dir, generated_dir, scores_dir,
                                               classify_dir)))
    data = collect(params, inputs)
    out_dir = Path(out_dir)
    build = out_dir / ".build.tmp"
    shutil.rmtree(build, ignore_errors=True)
    for folder in ("figures", "plots"):
        (build / folder).mkdir(parents=True)
    figures = write_figures(data, inputs.generated, build / "figures")
    context = page_context(data, figures, params)
    page, summary = render_page("report", context)
    (build / "index.html").write_text(page)
    (build / "summary.md").write_text(summary)
    metrics = headline_metrics(data)
    write_json(build / "metrics.json", metrics)
    write_json(build / "timings.json", timings_record(data["timings"]))
    data["training"].to_csv(build / "plots" / "training.csv", index=False)
    _publish(build, out_dir)
    print("report: verdicts")
    for item in context["verdicts"]:
        print(f"  {item['line']}")
    print(f"report: {out_dir / 'index.html'}, summary.md, metrics.json, timings.json, plots/training.csv and "
          f"{sum(figures.values())} figures in {out_dir / 'figures'}")
    return metrics


def _publish(build: Path, out_dir: Path) -> None:
    """Move the finished report from ``build`` into ``out_dir``: each folder by one rename, each file by an
    atomic replace (other files in ``out_dir``, such as its README, are kept)."""
    for folder in ("figures", "plots"):
        old = out_dir / f".{folder}.old"
        shutil.rmtree(old, ignore_errors=True)
        if (out_dir / folder).exists():
            (out_dir / folder).rename(old)
        (build / folder).rename(out_dir / folder)
        shutil.rmtree(old, ignore_errors=True)
    for name in ("metrics.json", "timings.json", "summary.md", "index.html"):
        (build / name).replace(out_dir / name)
    shutil.rmtree(build, ignore_errors=True)
