"""Report stage: one self-contained page that says what this run did and what it found.

``run_report`` reads only the folders named on its command line (ingest, pairs, models, generated,
scores, classify), collects every number the page shows into one dictionary (:func:`collect`) and
writes into ``out_dir``:

* ``index.html`` and ``summary.md``: rendered from the Jinja2 templates ``report.html`` / ``report.md``
  in ``vtgen/io/templates`` (HTML autoescaped), figures beside them in ``figures/``;
* ``metrics.json``: the headline numbers only (:func:`vtgen.io.report_metrics.headline_metrics`), plain
  numbers with sorted keys, so identical inputs give a byte-identical file for ``dvc metrics diff``;
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

This module reads the run and assembles the page; the parts live in :mod:`vtgen.io.report_verdicts`
(the first screen), :mod:`vtgen.io.report_tables`, :mod:`vtgen.io.report_figures`,
:mod:`vtgen.io.report_metrics` (metrics.json) and :mod:`vtgen.io.report_pages` (rendering).
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

import numpy as np
import pandas as pd
import yaml

from vtgen.core.domain import direction_producing, DIRECTIONS, MODALITIES
from vtgen.io.timing import read_with_times
from vtgen.io.images import read_rgb8
from vtgen.io.provenance import code_version
from vtgen.io.report_figures import write_figures
from vtgen.io.report_metrics import headline_metrics, realistic_gan_tests
from vtgen.io.report_pages import plain, read_json, render_page, table_view, write_json
from vtgen.io.report_tables import (
    accuracy_table, capacity_view, comparison_table, distribution_table, final_accuracy_table, memorisation_table,
    models_table, paper_table, SETTING_ORDER, ssim_name, ssim_tables,
)
from vtgen.io.report_verdicts import not_scored, policy_rows, recipe_advice, verdict_grid, verdict_lines
from vtgen.io.tables import PAIR_KINDS, QUARANTINE_COLUMNS, read_table

BY_CLASS_KEYS = ["direction", "scope", "candidate", "class"]
BY_CLASS_NEEDS = [*BY_CLASS_KEYS, "colour_ssim", "grey_ssim", "psnr", "ms_ssim", "set_colour_ssim",
                  "nearest_real_colour_ssim", "images"]
ACCURACY_NEEDS = ["modality", "setting", "seed", "epoch", "test_accuracy", "gan_test_accuracy"]
CLASSIFY_BY_CLASS_NEEDS = ["modality", "setting", "class", "images", "accuracy", "low", "high", "seeds"]
DISTRIBUTION_NEEDS = ["direction", "scope", "class", "candidate", "view", "metric", "value", "low", "high", "n",
                      "n_reference"]
MEMORISATION_NEEDS = ["direction", "class", "view", "candidate", "rate", "nearest_is_train_share", "n", "n_train"]
NEAREST_TRAINING_NEEDS = ["direction", "view", "rank", "generated_path", "train_path", "generated_class", "train_class",
                          "distance", "threshold", "flagged"]
PAIR_NEEDS = ["direction", "split", "class", "aligned"]
TRAINING_COLUMNS = ["step", "model", "loss_d", "loss_g_gan", "loss_g_l1"]


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
    """train.json of every model under ``models_dir/<direction>/<scope>/``, with the times of its timing.json put back
    where train.json had them before they moved there (wall seconds, seconds per step, capacity's seconds), in
    direction then scope order."""
    runs = [read_with_times(path) | {"folder": path.parent} for path in models_dir.glob("*/*/train.json")]
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



def _optional_columns(path: Path, keys: list[str], needs: list[str], what: str) -> pd.DataFrame:
    """A stage table that may be empty with its key columns only (a stage with nothing to do); when it
    has rows, every column of ``needs`` must be there."""
    table = read_table(path, keys, what)
    return read_table(path, needs, what) if len(table) else table.reindex(columns=needs)


def nearest_pictures(scores: Path, nearest: pd.DataFrame) -> dict[str, np.ndarray]:
    """{direction: the score stage's ``nearest_training_<direction>.png`` strip} for each direction with rows in
    ``nearest``: 2 rows of square images (generated on top, training below), one column per row of the table.
    ValueError naming the file where it is missing or its shape does not match the table."""
    found = {}
    for direction, rows in nearest.groupby("direction"):
        path = scores / f"nearest_training_{direction}.png"
        if not path.is_file():
            raise ValueError(f"{path} is missing: the score stage writes it beside nearest_training.parquet, "
                             f"which lists {len(rows)} {direction} pairs; run the score stage again")
        pictures = read_rgb8(path).rgb
        side = pictures.shape[0] // 2
        if pictures.shape[0] != 2 * side or pictures.shape[1] != len(rows) * side:
            raise ValueError(f"{path} is {pictures.shape[1]} x {pictures.shape[0]} px, not 2 rows of {len(rows)} "
                             f"square images as nearest_training.parquet lists; run the score stage again")
        found[str(direction)] = pictures
    return found


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
            "preset": params["translation"]["preset"], "recipe": params["translation"]["recipe"], "recipe_reason": "as set",
            "scope": list(params["translation"]["scope"])}


def collect(params: dict, inputs: ReportInputs) -> dict:
    """Every number and table the report shows, read from the input folders only."""
    runs = model_runs(inputs.models)
    classify = classification(inputs.classify)
    synthetic = params["dataset"]["source"] == "synthetic"
    nearest = read_table(inputs.scores / "nearest_training.parquet", NEAREST_TRAINING_NEEDS,
                         "the score stage's nearest-training table")
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
        "nearest_training": nearest, "nearest_pictures": nearest_pictures(inputs.scores, nearest),
        "classify": classify, "realistic_gan_test": realistic_gan_tests(classify, runs),
        "read_class": {d: read_class_counts(read_json(inputs.generated / d / "summary.json"))
                       for d in DIRECTIONS if (inputs.generated / d / "summary.json").is_file()},
        "timings": stage_timings(inputs, runs),
    }


# ---------------------------------------------------------------- the page


def read_class_counts(generate_summary: dict | None) -> dict | None:
    """The generate stage's ``told_the_class_read`` summed over its scopes: {reader, inputs, read_correctly};
    None where it translated no input told the class read from it."""
    entries = [e["told_the_class_read"] for e in ((generate_summary or {}).get("scopes") or {}).values()
               if isinstance(e, dict) and e.get("told_the_class_read")]
    if not entries:
        return None
    return {"reader": ", ".join(sorted({e["reader"] for e in entries})),
            "inputs": sum(e["inputs"] for e in entries), "read_correctly": sum(e["read_correctly"] for e in entries)}


def conditioned_gan_test_note(modality: str, summary: dict, runs: list[dict], read: dict | None = None) -> str | None:
    """A caveat for the GAN-test of ``modality`` when the generator that made its images was told a class
    (train.json ``conditioning`` other than none): told each image's class (``class``, ``reference``), its
    images can be easier to classify than real ones, and where the classify stage scored the same inputs told
    the class a reader read from each (summary ``gan_test_read``; ``read``: :func:`read_class_counts`), that
    GAN-test is given as the one of a generator not told the class (issue 24, goal 3); told what a reader of
    the input read (``inferred``, train.json ``input_reader``), they can be no more recognisable than that
    reading. Either way the GAN-test is read against the real-only test accuracy; None when no generator was
    told a class."""
    made_by = [r for r in runs if r.get("direction") == direction_producing(modality) and r.get("status", "ok") == "ok"]
    kinds = sorted({r.get("conditioning", "none") for r in made_by} - {"none"})
    gan, real = summary.get("gan_test") or {}, (summary.get("settings") or {}).get("real") or {}
    if not kinds or gan.get("final_mean") is None or real.get("final_mean") is None:
        return None
    if kinds == ["inferred"]:
        readers = sorted({r.get("input_reader", "network") for r in made_by})
        return (f"the generator of these images was told the class its input reader ({', '.join(readers)}) read from "
                f"each input, never the image's own class (conditioning inferred), so the GAN-test "
                f"({gan['final_mean']:.3f}) is bounded by how well the inputs can be read; read it against the "
                f"real-only test accuracy ({real['final_mean']:.3f})")
    note = (f"the generator of these images was told each image's class (conditioning {', '.join(kinds)}), so the "
            f"GAN-test ({gan['final_mean']:.3f}) shows in part that it follows the class it is given; read it against "
            f"the real-only test accuracy ({real['final_mean']:.3f}), not as realism alone")
    told_read = summary.get("gan_test_read") or {}
    if told_read.get("final_mean") is None:
        return note
    low, high = told_read.get("interval") or (float("nan"), float("nan"))
    reader = {"features": "hand-crafted-feature"}.get(read["reader"], read["reader"]) if read else ""
    reading = (f"the class a {reader} reader reads from each input (its own class for "
               f"{read['read_correctly']} of {read['inputs']})" if read else "the class a reader reads from each input")
    return (f"{note}. Told instead {reading}, as a generator not told the class would be, its {told_read['images']} "
            f"test translations score a GAN-test of {told_read['final_mean']:.3f} [{low:.3f}, {high:.3f}]: the "
            f"figure issue 24's goal 3 reads")


def realistic_gan_test_note(modality: str, summary: dict, oracle: dict | None) -> str | None:
    """What the GAN-test of ``modality`` would be with real held-out images in place of the translations
    (``oracle``: one entry of :func:`vtgen.io.report_metrics.realistic_gan_tests`), beside the GAN-test."""
    gan = (summary.get("gan_test") or {}).get("final_mean")
    if not oracle or gan is None:
        return None
    source = DIRECTIONS[direction_producing(modality)][0]
    of_class = ("its input's own class (the generator was told it)" if oracle["told_class"] else
                f"the class the {source} real-only classifier reads from its input (a generator told nothing can "
                f"know no more of the class than its input shows)")
    return (f"realistic GAN-test {oracle['value']:.3f} beside the GAN-test's {gan:.3f}: the score had each translation "
            f"been a real held-out {modality} image of {of_class}, by this stage's real-only classifiers (expected over "
            f"n = {oracle['inputs']} test inputs). A GAN-test well below it is the generator's shortfall; at it, "
            f"the data allows no more")


def _classify_view(modality: str, entry: dict, runs: list[dict], oracle: dict | None = None,
                   read: dict | None = None) -> dict:
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
                                                  f"when the paired 95% interval of the difference excludes 0"))
        seeds = sorted(plain(s) for s in table["seed"].unique())
        tables.append(table_view(accuracy_table(table, modality, n, gan_n),
                                 f"Table III ({modality}): test accuracy after each iteration, mean ± std over seeds "
                                 f"{seeds} [95% Wilson interval on n = {n if n else '?'} real test images"
                                 + (f", {gan_n} generated for the GAN-test" if gan_n else "")
                                 + "], beside the paper's values at the same iteration"))
    caveats = [conditioned_gan_test_note(modality, summary, runs, read),
               realistic_gan_test_note(modality, summary, oracle)]
    caveats = [c for c in caveats if c] if status == "ok" else []
    return {"modality": modality, "status": status, "tables": tables, "at_chance": entry["at_chance"],
            "classes": len(summary.get("classes", [])), "notes": summary.get("notes", []) + caveats}


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
        "policy": policy_rows(data), "verdict_grid": verdict_grid(data), "recipe_advice": recipe_advice(data),
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
        "classify": [_classify_view(m, e, data["models"], (data.get("realistic_gan_test") or {}).get(m),
                                    (data.get("read_class") or {}).get(direction_producing(m)))
                     for m, e in data["classify"].items()],
        "timings": table_view(timings[["job", "seconds", "finished"]],
                              "Wall time of each job (timing.json in its output folder)") if not timings.empty else None,
    }


def timings_record(timings: pd.DataFrame) -> dict:
    """timings.json: the jobs in pipeline order and their total wall seconds."""
    jobs = [{k: plain(v) for k, v in row.items()} for row in timings.to_dict("records")]
    return {"jobs": jobs, "total_seconds": round(float(timings["seconds"].sum()), 2)}


def run_report(params: dict, ingest_dir, pairs_dir, models_dir, generated_dir, scores_dir, classify_dir,
               out_dir: str | Path = "reports", recipe_reason: str = "as set") -> dict:
    """Build index.html, summary.md, metrics.json, timings.json, plots/training.csv and figures/ in
    ``out_dir`` from the named stage folders only; return the headline metrics. ``recipe_reason``: why the run
    applied its recipe (:func:`vtgen.io.params.recipe_choice`), shown beside its name."""
    inputs = ReportInputs(*(Path(p) for p in (ingest_dir, pairs_dir, models_dir, generated_dir, scores_dir,
                                               classify_dir)))
    data = collect(params, inputs)
    data["run"]["recipe_reason"] = recipe_reason
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
