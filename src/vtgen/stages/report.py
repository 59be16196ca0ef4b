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

The page holds data provenance (synthetic or real, counts, quarantined inputs), the parameters and
code version, the shape of the paper's Table I (V2T), Table II (T2V) and Table III (classification
per iteration) with the paper's published ranges and the reference levels, image grids per class
and direction (the generate stage's ``preview.png``), training-loss curves and stage timings.
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

from vtgen.core.domain import DIRECTIONS, MODALITIES  # noqa: E402
from vtgen.io.provenance import code_version  # noqa: E402
from vtgen.io.report_pages import PAPER, plain, read_json, render_page, table_view, write_json  # noqa: E402
from vtgen.io.tables import QUARANTINE_COLUMNS, candidate_label, read_table  # noqa: E402

SETTING_ORDER = ["real", "real+generated", "low-data real", "low-data real+generated"]
REFERENCE_LEVELS = {"real_train": "real_vs_real", "nearest_neighbour": "nearest_neighbour",
                    "mean_image": "mean_image", "flat_mean_colour": "flat_mean_colour"}
BY_CLASS_NEEDS = ["direction", "scope", "candidate", "class", "colour_ssim", "grey_ssim", "psnr", "ms_ssim",
                  "set_colour_ssim", "nearest_real_colour_ssim", "images"]
ACCURACY_NEEDS = ["modality", "setting", "seed", "epoch", "test_accuracy", "gan_test_accuracy"]
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
        found[modality] = {"summary": summary, "accuracy": accuracy, "at_chance": at_chance(summary, accuracy)}
    return found


def at_chance(summary: dict, accuracy: pd.DataFrame) -> list[str]:
    """Settings the classify stage marked as ending at chance level (summary or table); none when unmarked."""
    flagged = {name for name, entry in (summary.get("settings") or {}).items()
               if isinstance(entry, dict) and entry.get("at_chance") is True}
    if "at_chance" in accuracy.columns:
        flagged |= set(accuracy.loc[accuracy["at_chance"].fillna(False).astype(bool), "setting"])
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
        "score_summary": read_json(inputs.scores / "summary.json"),
        "by_class": read_table(inputs.scores / "by_class.parquet", BY_CLASS_NEEDS, "the score stage's by_class table"),
        "classify": classification(inputs.classify), "timings": stage_timings(inputs, runs),
    }


# ---------------------------------------------------------------- headline numbers (metrics.json)


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


def classify_headline(entry: dict) -> dict:
    """Mean final-epoch test accuracy over seeds per setting, the GAN-test and the test-set size."""
    table, summary = entry["accuracy"], entry["summary"]
    if summary.get("status", "ok") != "ok" or table.empty:
        return {}
    last = table[table["epoch"] == table["epoch"].max()]
    result = {s: _number(g["test_accuracy"].mean()) for s, g in last.groupby("setting")}
    gan = last.loc[(last["setting"] == "real"), "gan_test_accuracy"].dropna()
    result["gan_test"] = _number(gan.mean()) if len(gan) else None
    result["seeds"] = int(last["seed"].nunique())
    result["real_test_images"] = (summary.get("counts") or {}).get("real_test")
    return _compact(result)


def headline_metrics(data: dict) -> dict:
    """The numbers for ``dvc metrics``: Colour-SSIM per direction, accuracy per modality and counts; no
    timings, dates, versions or paths."""
    metrics = {d: ssim_headline(data["by_class"], d) for d in DIRECTIONS}
    metrics["classify"] = _compact({m: classify_headline(e) for m, e in data["classify"].items()})
    ingest = data["ingest"]
    metrics["counts"] = _compact({"classes": len(ingest.get("classes", [])), "images_kept": ingest.get("kept"),
                                  "quarantined": ingest.get("quarantined"), "models": len(data["models"])})
    return metrics


# ---------------------------------------------------------------- tables


def ssim_tables(by_class: pd.DataFrame, direction: str) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """The paper-shaped tables of one direction: set-to-set Colour-SSIM (the paper's protocol) and,
    when the data has ground truth, the aligned scores; one row per class plus ``(all)``."""
    rows = by_class[by_class["direction"] == direction]
    classes = sorted(c for c in rows["class"].unique() if c != "(all)") + ["(all)"]
    scopes = sorted(rows.loc[rows["candidate"] == "generated", "scope"].unique())

    def column(candidate: str, metric: str, scope: str = "-") -> list:
        part = rows[(rows["candidate"] == candidate) & (rows["scope"] == scope)].set_index("class")[metric]
        return [part.get(c, np.nan) for c in classes]

    def suffix(scope: str) -> str:
        return "" if len(scopes) == 1 else f" [{scope}]"

    set_table = pd.DataFrame({"class": classes})
    for scope in scopes:
        set_table[f"generated{suffix(scope)}"] = column("generated", "set_colour_ssim", scope)
        set_table[f"generated, nearest real{suffix(scope)}"] = column("generated", "nearest_real_colour_ssim", scope)
    set_table["real vs real"] = column("real_train", "set_colour_ssim")
    for candidate in ("nearest_neighbour", "mean_image", "flat_mean_colour"):
        set_table[candidate.replace("_", " ")] = column(candidate, "set_colour_ssim")
    set_table["paper"] = ["" for _ in classes[:-1]] + [PAPER["colour_ssim"][direction]]
    if rows.loc[rows["candidate"] == "generated", "colour_ssim"].notna().sum() == 0:
        return set_table, None
    aligned = pd.DataFrame({"class": classes})
    for scope in scopes:
        for metric, label in (("colour_ssim", "Colour-SSIM"), ("grey_ssim", "grey SSIM"), ("psnr", "PSNR dB"),
                              ("ms_ssim", "MS-SSIM")):
            values = column("generated", metric, scope)
            if metric != "ms_ssim" or np.isfinite(np.asarray(values, dtype=float)).any():
                aligned[f"{label}{suffix(scope)}"] = values
    for candidate in ("nearest_neighbour", "mean_image", "flat_mean_colour"):
        aligned[f"{candidate.replace('_', ' ')} Colour-SSIM"] = column(candidate, "colour_ssim")
    return set_table, aligned


def _mean_std_cells(values: pd.DataFrame, column: str, epochs) -> list[str]:
    stats = values.groupby("epoch")[column].agg(["mean", "std"])
    return [f"{stats.loc[e, 'mean']:.3f} ± {np.nan_to_num(stats.loc[e, 'std']):.3f}" if e in stats.index else ""
            for e in epochs]


def accuracy_table(accuracy: pd.DataFrame, modality: str) -> pd.DataFrame:
    """Table III shape: test accuracy after each epoch (mean ± std over seeds) per setting, and the GAN-test."""
    part = accuracy[accuracy["modality"] == modality]
    table = pd.DataFrame({"epoch": sorted(part["epoch"].unique())})
    for setting in [s for s in SETTING_ORDER if s in set(part["setting"])]:
        table[setting] = _mean_std_cells(part[part["setting"] == setting], "test_accuracy", table["epoch"])
    gan = part[(part["setting"] == "real") & part["gan_test_accuracy"].notna()]
    if not gan.empty:
        table["GAN-test (real-only classifier on generated)"] = _mean_std_cells(gan, "gan_test_accuracy",
                                                                                table["epoch"])
    table["paper"] = [""] * (len(table) - 1) + [PAPER["accuracy"][modality]]
    return table


def models_table(runs: list[dict]) -> pd.DataFrame:
    """One row per trained generator from its train.json."""
    return pd.DataFrame([{
        "model": f"{r['direction']}/{r['scope']}", "preset": r.get("preset"), "size": r["settings"]["size"],
        "iterations": r["steps"], "wall s": r.get("wall_seconds"), "s/iteration": r.get("seconds_per_iteration"),
        "final val L1": r.get("final_val_l1"), "device": r.get("device"), "precision": r.get("precision"),
    } for r in runs])


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


def scores_figure(by_class: pd.DataFrame, path: Path) -> None:
    """Set-to-set and aligned Colour-SSIM of every candidate over all classes, one panel per direction."""
    overall = by_class[by_class["class"] == "(all)"]
    fig, axes = plt.subplots(1, len(DIRECTIONS), figsize=(11, 3.6), squeeze=False)
    for ax, direction in zip(axes[0], DIRECTIONS):
        part = overall[overall["direction"] == direction]
        labels = [candidate_label(c, s).replace("_", " ") for c, s in zip(part["candidate"], part["scope"])]
        y = np.arange(len(part))
        ax.barh(y - 0.2, part["set_colour_ssim"], height=0.4, label="set-to-set (paper protocol)")
        ax.barh(y + 0.2, part["colour_ssim"].fillna(0), height=0.4, label="aligned (own ground truth)")
        ax.set_yticks(y, labels, fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel("Colour-SSIM")
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
        for setting in [s for s in SETTING_ORDER if s in set(part["setting"])]:
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
        scores_figure(data["by_class"], figures / "scores.png")
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


def _classify_view(modality: str, entry: dict) -> dict:
    summary, table = entry["summary"], entry["accuracy"]
    status = summary.get("status", "ok")
    view = None
    if status == "ok" and not table.empty:
        view = table_view(accuracy_table(table, modality),
                          f"Table III ({modality}): test accuracy after each iteration, mean ± std over seeds "
                          f"{sorted(plain(s) for s in table['seed'].unique())}")
    return {"modality": modality, "status": status, "table": view, "at_chance": entry["at_chance"],
            "classes": len(summary.get("classes", [])), "notes": summary.get("notes", [])}


def _ssim_view(by_class: pd.DataFrame, number: str, direction: str) -> dict:
    set_table, aligned = ssim_tables(by_class, direction)
    name = "visual to tactile (seeing to feel)" if direction == "v2t" else "tactile to visual (touching to see)"
    return {"direction": direction, "set": table_view(set_table, f"Table {number}: {direction.upper()}, {name}: "
                                                                  f"set-to-set Colour-SSIM per class"),
            "aligned": None if aligned is None else table_view(
                aligned, f"Table {number}b: {direction.upper()}: aligned scores against each output's own ground truth")}


def page_context(data: dict, figures: dict[str, bool]) -> dict:
    """What the report templates render: ``data`` with its tables as template data."""
    quarantine, timings, by_class = data["quarantine"], data["timings"], data["by_class"]
    ms_ssim = data["score_summary"].get("ms_ssim", "computed")
    return {
        **{k: data[k] for k in ("title", "synthetic", "dataset", "ingest", "pairs", "run", "params_yaml")},
        "directions": list(DIRECTIONS), "figures": figures,
        "quarantine": table_view(quarantine.head(30), f"Quarantined inputs ({len(quarantine)}; first 30 shown)")
        if not quarantine.empty else None,
        "models": table_view(models_table(data["models"]), "Trained generators (train.json)"),
        "ms_ssim_note": None if ms_ssim == "computed" else f"MS-SSIM {ms_ssim}.",
        "ssim": [_ssim_view(by_class, n, d) for n, d in (("I", "v2t"), ("II", "t2v")) if d in set(by_class["direction"])],
        "classify": [_classify_view(m, e) for m, e in data["classify"].items()],
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
    page, summary = render_page("report", page_context(data, figures))
    (build / "index.html").write_text(page)
    (build / "summary.md").write_text(summary)
    metrics = headline_metrics(data)
    write_json(build / "metrics.json", metrics)
    write_json(build / "timings.json", timings_record(data["timings"]))
    data["training"].to_csv(build / "plots" / "training.csv", index=False)
    _publish(build, out_dir)
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
