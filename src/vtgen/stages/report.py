"""Report stage: one self-contained page that says what this run did and what it found.

``run_report`` reads the outputs of every earlier stage (paths in ``RUN_LAYOUT``, relative to the
project root) and writes ``reports/index.html`` (figures beside it in ``reports/figures/``, no
network needed), ``reports/summary.md`` and ``reports/metrics.json`` (for ``dvc metrics``).

The page holds: data provenance (synthetic or real, counts, quarantined inputs), the parameters
and code version, the shape of the paper's Table I (V2T), Table II (T2V) and Table III
(classification per iteration) with the paper's published figures beside ours and the reference
levels, image grids per class and direction, training-loss curves and the time of every stage.
"""

from __future__ import annotations

import datetime as dt
import html
import json
import os
import platform
import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
import yaml  # noqa: E402
from PIL import Image  # noqa: E402

from vtgen.io.provenance import code_version
from vtgen.io.images import labelled_sheet, write_png
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import candidate_label

RUN_LAYOUT = {
    "ingest": Path("data/ingest"),
    "pairs": Path("data/pairs"),
    "models": Path("models"),
    "generated": Path("data/generated"),
    "scores": Path("data/scores"),
    "classify": Path("data/classify"),
    "benchmarks": Path("logs/benchmarks"),
}
MODALITIES = ("visual", "tactile")

# The paper's published figures. Only the ranges below could be checked offline (the project
# guide's summary of Lee, Bollegala & Luo, ICRA 2019); per-row values of its tables are not
# reproduced here rather than guessed.
PAPER = {
    "citation": "Lee, Bollegala and Luo, \"Touching to See and Seeing to Feel\", ICRA 2019",
    "note": "ranges as summarised in the project guide; the per-row values of the paper's tables could not be "
            "checked offline and are not guessed",
    "colour_ssim": {"v2t": "about 0.90", "t2v": "0.77 (cloth types) to 0.91"},
    "accuracy": {"visual": "0.96 to 0.99", "tactile": "0.78 to 0.91"},
}
SETTING_ORDER = ["real", "real+generated", "low-data real", "low-data real+generated"]


# ---------------------------------------------------------------- reading the run


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def model_runs(models_root: Path) -> list[dict]:
    """train.json of every trained model, with its dvclive loss tables (DataFrames by metric name)."""
    runs = []
    for train_json in sorted(models_root.glob("*/*/train.json")):
        run = json.loads(train_json.read_text())
        curves = {}
        for tsv in sorted((train_json.parent / "dvclive" / "plots" / "metrics").rglob("*.tsv")):
            name = str(tsv.relative_to(train_json.parent / "dvclive" / "plots" / "metrics").with_suffix(""))
            curves[name] = pd.read_csv(tsv, sep="\t")
        run["curves"] = curves
        runs.append(run)
    return runs


STAGE_ORDER = ["render", "ingest", "roi", "pairs", "train", "generate", "score", "classify", "report"]


def stage_timings(benchmarks: Path) -> pd.DataFrame:
    """Wall seconds and peak memory of each job from Snakemake's benchmark files (empty when absent),
    in pipeline order."""
    def order(tsv: Path) -> tuple[int, str]:
        stage = tsv.stem.split("_")[0]
        return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER), tsv.stem)

    rows = []
    for tsv in sorted(benchmarks.glob("*.tsv"), key=order):
        table = pd.read_csv(tsv, sep="\t")
        if table.empty:
            continue
        rows.append({"job": tsv.stem, "seconds": float(table["s"].iloc[-1]),
                     "max_rss_mb": float(table["max_rss"].iloc[-1]) if "max_rss" in table else np.nan})
    return pd.DataFrame(rows, columns=["job", "seconds", "max_rss_mb"])


# ---------------------------------------------------------------- tables


def fmt(value, digits: int = 3) -> str:
    if value is None or (isinstance(value, float) and not np.isfinite(value)):
        return "—" if value is None or np.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, (float, np.floating)):
        return f"{value:.{digits}f}"
    return str(value)


def ssim_tables(by_class: pd.DataFrame, direction: str) -> tuple[pd.DataFrame, pd.DataFrame | None]:
    """The paper-shaped tables of one direction: set-to-set Colour-SSIM (the paper's protocol) and,
    when the data has ground truth, the aligned scores; one row per class plus ``(all)``."""
    rows = by_class[by_class["direction"] == direction]
    classes = sorted(c for c in rows["class"].unique() if c != "(all)") + ["(all)"]
    generated = rows[rows["candidate"] == "generated"]
    scopes = sorted(generated["scope"].unique())

    def column(candidate: str, metric: str, scope: str = "-") -> list:
        part = rows[(rows["candidate"] == candidate) & (rows["scope"] == scope)].set_index("class")[metric]
        return [part.get(c, np.nan) for c in classes]

    set_table = pd.DataFrame({"class": classes})
    for scope in scopes:
        suffix = "" if len(scopes) == 1 else f" [{scope}]"
        set_table[f"generated{suffix}"] = column("generated", "set_colour_ssim", scope)
        set_table[f"generated, nearest real{suffix}"] = column("generated", "nearest_real_colour_ssim", scope)
    set_table["real vs real"] = column("real_train", "set_colour_ssim")
    for candidate in ("nearest_neighbour", "mean_image", "flat_mean_colour"):
        set_table[candidate.replace("_", " ")] = column(candidate, "set_colour_ssim")
    set_table["paper"] = ["" for _ in classes[:-1]] + [PAPER["colour_ssim"][direction]]

    if generated["colour_ssim"].notna().sum() == 0:
        return set_table, None
    aligned = pd.DataFrame({"class": classes})
    for scope in scopes:
        suffix = "" if len(scopes) == 1 else f" [{scope}]"
        for metric, label in (("colour_ssim", "Colour-SSIM"), ("grey_ssim", "grey SSIM"), ("psnr", "PSNR dB"),
                              ("ms_ssim", "MS-SSIM")):
            values = column("generated", metric, scope)
            if metric != "ms_ssim" or np.isfinite(np.asarray(values, dtype=float)).any():
                aligned[f"{label}{suffix}"] = values
    for candidate in ("nearest_neighbour", "mean_image", "flat_mean_colour"):
        aligned[f"{candidate.replace('_', ' ')} Colour-SSIM"] = column(candidate, "colour_ssim")
    return set_table, aligned


def accuracy_table(accuracy: pd.DataFrame, modality: str) -> pd.DataFrame:
    """Table III shape: test accuracy after each epoch (mean ± std over seeds) per setting, and the GAN-test."""
    part = accuracy[accuracy["modality"] == modality]
    table = pd.DataFrame({"epoch": sorted(part["epoch"].unique())})
    for setting in [s for s in SETTING_ORDER if s in set(part["setting"])]:
        stats = part[part["setting"] == setting].groupby("epoch")["test_accuracy"].agg(["mean", "std"])
        table[setting] = [f"{stats.loc[e, 'mean']:.3f} ± {np.nan_to_num(stats.loc[e, 'std']):.3f}" for e in table["epoch"]]
    gan = part[(part["setting"] == "real") & part["gan_test_accuracy"].notna()]
    if not gan.empty:
        stats = gan.groupby("epoch")["gan_test_accuracy"].agg(["mean", "std"])
        table["GAN-test (real-only classifier on generated)"] = [
            f"{stats.loc[e, 'mean']:.3f} ± {np.nan_to_num(stats.loc[e, 'std']):.3f}" for e in table["epoch"]]
    table["paper"] = [""] * (len(table) - 1) + [PAPER["accuracy"][modality]]
    return table


def html_table(table: pd.DataFrame, caption: str) -> str:
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in table.columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(v))}</td>" for v in row) + "</tr>"
                   for row in table.itertuples(index=False))
    return f"<table><caption>{html.escape(caption)}</caption><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def markdown_table(table: pd.DataFrame) -> str:
    lines = ["| " + " | ".join(map(str, table.columns)) + " |", "|" + "---|" * len(table.columns)]
    lines += ["| " + " | ".join(fmt(v) for v in row) + " |" for row in table.itertuples(index=False)]
    return "\n".join(lines)


# ---------------------------------------------------------------- figures


def image_grid(generated: pd.DataFrame, scores: pd.DataFrame | None, direction: str, per_class: int = 2) -> np.ndarray:
    """Per class: inputs | generated | ground truth, or the nearest real test image when there is none."""
    source, target = DIRECTIONS[direction]
    test = generated[generated["split"] == "test"].sort_values(["class", "scope", "input_path"])
    nearest = {}
    if scores is not None:
        gen_scores = scores[(scores["direction"] == direction) & (scores["candidate"] == "generated")]
        nearest = dict(zip(gen_scores["image"], gen_scores["nearest_real_path"]))
    has_truth = (test["ground_truth_path"].fillna("") != "").any()

    def load(path: str):
        if not path or not Path(path).is_file():
            return None
        with Image.open(path) as image:
            return np.asarray(image.convert("RGB"))

    rows = []
    for name, group in test.groupby("class", sort=True):
        group = group.head(per_class)
        reference = [load(p) for p in (group["ground_truth_path"].fillna("") if has_truth
                                       else [nearest.get(o, "") for o in group["output_path"]])]
        rows.append((name, [[load(p) for p in group["input_path"]], [load(p) for p in group["output_path"]],
                            reference]))
    titles = [f"input ({source})", f"generated ({target})",
              f"ground truth ({target})" if has_truth else f"nearest real test ({target})"]
    return labelled_sheet(rows, titles, per_group=per_class)


def _save_figure(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def loss_figure(runs: list[dict], path: Path, max_models: int = 6) -> None:
    shown = runs[:max_models]
    fig, axes = plt.subplots(len(shown), 2, figsize=(10, 2.6 * len(shown)), squeeze=False)
    for (ax_gan, ax_l1), run in zip(axes, shown):
        label = f"{run['direction']}/{run['scope']}"
        for name in ("train/loss_d", "train/loss_g_gan"):
            if name in run["curves"]:
                table = run["curves"][name]
                ax_gan.plot(table["step"], table.iloc[:, 1], label=name.split("/")[1])
        for name in ("train/loss_g_l1", "val/l1"):
            if name in run["curves"]:
                table = run["curves"][name]
                ax_l1.plot(table["step"], table.iloc[:, 1], label=name.replace("/", " "),
                           marker="o" if name.startswith("val") else None)
        ax_gan.set_title(f"{label}: adversarial losses")
        ax_l1.set_title(f"{label}: L1 error (train, validation)")
        for ax in (ax_gan, ax_l1):
            ax.set_xlabel("iteration")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
    _save_figure(fig, path)


def scores_figure(by_class: pd.DataFrame, path: Path) -> None:
    overall = by_class[by_class["class"] == "(all)"]
    fig, axes = plt.subplots(1, len(DIRECTIONS), figsize=(11, 3.6), squeeze=False)
    for ax, direction in zip(axes[0], DIRECTIONS):
        part = overall[overall["direction"] == direction]
        labels = [candidate_label(c, s) for c, s in zip(part["candidate"], part["scope"])]
        y = np.arange(len(part))
        ax.barh(y - 0.2, part["set_colour_ssim"], height=0.4, label="set-to-set (paper protocol)")
        ax.barh(y + 0.2, part["colour_ssim"].fillna(0), height=0.4, label="aligned (own ground truth)")
        ax.set_yticks(y, [label.replace("_", " ") for label in labels], fontsize=8)
        ax.invert_yaxis()
        ax.set_xlim(0, 1)
        ax.set_xlabel("Colour-SSIM")
        ax.set_title(direction.upper())
        ax.grid(axis="x", alpha=0.3)
    axes[0][0].legend(fontsize=8, loc="lower right")
    _save_figure(fig, path)


def accuracy_figure(accuracy: pd.DataFrame, path: Path) -> None:
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
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(timings) + 1.2))
    ax.barh(timings["job"], timings["seconds"])
    ax.invert_yaxis()
    ax.set_xlabel("wall seconds (last run of each job)")
    ax.grid(axis="x", alpha=0.3)
    _save_figure(fig, path)


# ---------------------------------------------------------------- assembling the report


STYLE = """
body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:0.8em 0 1.6em;font-size:0.85em}
caption{text-align:left;font-weight:600;padding:0.3em 0}
th,td{border:1px solid #bbb;padding:0.25em 0.55em;text-align:right}
th:first-child,td:first-child{text-align:left}
img{max-width:100%;border:1px solid #ddd}
.banner{background:#fff3cd;border:1px solid #e0c36a;padding:0.6em 1em;font-weight:600}
.note{color:#555;font-size:0.9em}
pre{background:#f5f5f5;padding:0.8em;overflow-x:auto;font-size:0.8em}
"""


class _Page:
    """Collects the report once and renders it as HTML and as Markdown."""

    def __init__(self) -> None:
        self.html: list[str] = []
        self.md: list[str] = []

    def heading(self, text: str, level: int = 2) -> None:
        self.html.append(f"<h{level}>{html.escape(text)}</h{level}>")
        self.md.append("#" * level + " " + text + "\n")

    def para(self, text: str, css: str = "") -> None:
        klass = f' class="{css}"' if css else ""
        self.html.append(f"<p{klass}>{html.escape(text)}</p>")
        self.md.append(text + "\n")

    def bullets(self, items: list[str]) -> None:
        self.html.append("<ul>" + "".join(f"<li>{html.escape(i)}</li>" for i in items) + "</ul>")
        self.md.append("\n".join(f"- {i}" for i in items) + "\n")

    def table(self, table: pd.DataFrame, caption: str) -> None:
        self.html.append(html_table(table, caption))
        self.md.append(f"**{caption}**\n\n{markdown_table(table)}\n")

    def figure(self, relative: str, alt: str) -> None:
        self.html.append(f'<figure><img src="{html.escape(relative)}" alt="{html.escape(alt)}">'
                         f"<figcaption class=\"note\">{html.escape(alt)}</figcaption></figure>")
        self.md.append(f"![{alt}]({relative})\n")

    def preformatted(self, text: str, summary: str) -> None:
        self.html.append(f"<details><summary>{html.escape(summary)}</summary><pre>{html.escape(text)}</pre></details>")
        self.md.append(f"<details><summary>{summary}</summary>\n\n```\n{text}\n```\n\n</details>\n")


def _provenance(page: _Page, params: dict) -> dict:
    layout = RUN_LAYOUT
    ingest = _read_json(layout["ingest"] / "summary.json") or {}
    pairs = _read_json(layout["pairs"] / "summary.json") or {}
    synthetic = params["dataset"]["source"] == "synthetic"
    page.heading("Data provenance")
    if synthetic:
        page.para("SYNTHETIC DATA: every number on this page comes from the embedded procedural ViTac-like dataset "
                  "rendered by vtgen, not from real visual or GelSight images.", "banner")
    page.bullets([
        f"dataset: {params['dataset']['source']} at {params['dataset']['path']}",
        f"images in: {ingest.get('entries_in', '?')}, kept: {ingest.get('kept', '?')}, "
        f"quarantined: {ingest.get('quarantined', '?')}, converted with a note: {ingest.get('with_note', '?')}",
        f"classes: {len(ingest.get('classes', []))} ({', '.join(ingest.get('classes', []))})",
        "tiles per split: " + ", ".join(f"{k} {v}" for k, v in pairs.get("tiles_per_split", {}).items()),
    ] + [f"{d.upper()} pairs: " + ", ".join(f"{s} {v['pairs']} ({v['aligned']} aligned)"
                                             for s, v in pairs.get(d, {}).items()) for d in DIRECTIONS]
      + [f"warning: {w}" for w in pairs.get("warnings", [])])
    quarantine = layout["ingest"] / "quarantine.parquet"
    if quarantine.is_file():
        table = pd.read_parquet(quarantine)
        if not table.empty:
            page.table(table.head(30), f"Quarantined inputs ({len(table)}; first 30 shown)")
    return {"synthetic": synthetic, "ingest": ingest, "pairs": pairs}


def run_report(params: dict, out_dir: str | Path = "reports") -> dict:
    """Build ``index.html``, ``summary.md``, ``metrics.json`` and ``figures/*.png`` in ``out_dir``
    from the run's stage outputs (paths in ``RUN_LAYOUT``); return the metrics."""
    layout = RUN_LAYOUT
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    build = out_dir / ".build.tmp"
    shutil.rmtree(build, ignore_errors=True)
    figures = build / "figures"
    figures.mkdir(parents=True)
    page = _Page()
    metrics: dict = {}

    provenance = _provenance(page, params)
    metrics["synthetic"] = provenance["synthetic"]

    page.heading("Run")
    page.bullets([f"code version: {code_version()}",
                  f"built: {dt.datetime.now(dt.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}",
                  f"python {platform.python_version()}, torch {torch.__version__}, {os.cpu_count()} CPUs",
                  f"translation preset: {params['translation']['preset']}, scope: "
                  f"{', '.join(params['translation']['scope'])}"])
    page.preformatted(yaml.safe_dump(params, sort_keys=False), "parameters (params.yaml as run)")
    page.html.append('<p>Studies outside the main job - the paper\'s experiment rows, the speed-accuracy trade, '
                     'capacity auto and the stability edge cases: <a href="studies/index.html">studies/index.html</a> '
                     '(built by <code>snakemake studies</code>).</p>')
    page.md.append("Studies outside the main job: [studies/index.html](studies/index.html) (built by `snakemake studies`).\n")

    # -- translation and training curves
    runs = model_runs(layout["models"])
    page.heading("Translation models")
    if runs:
        page.table(pd.DataFrame([{
            "model": f"{r['direction']}/{r['scope']}", "preset": r.get("preset"), "size": r["settings"]["size"],
            "iterations": r["steps"], "wall s": r.get("wall_seconds"), "s/iteration": r.get("seconds_per_iteration"),
            "final val L1": r.get("final_val_l1"), "device": r.get("device"), "precision": r.get("precision"),
        } for r in runs]), "Trained generators (train.json)")
        loss_figure(runs, figures / "losses.png")
        page.figure("figures/losses.png", "Training losses per iteration (dvclive logs of the train stage)")
    else:
        page.para("No trained models found under models/.")

    # -- Tables I and II
    by_class_path = layout["scores"] / "by_class.parquet"
    scores_path = layout["scores"] / "scores.parquet"
    by_class = pd.read_parquet(by_class_path) if by_class_path.is_file() else None
    scores = pd.read_parquet(scores_path) if scores_path.is_file() else None
    score_summary = _read_json(layout["scores"] / "summary.json") or {}
    page.heading("Generated data: Colour-SSIM with reference levels (Tables I and II)")
    page.para("Colour-SSIM is SSIM (Wang et al. 2004) per RGB channel, averaged: Gaussian window sigma 1.5, "
              "K1 0.01, K2 0.03, L 255. Set-to-set (the paper's protocol) scores each generated image against "
              "every real test image of its class; nearest real keeps the best match; aligned scores each output "
              "against its own ground truth where the data has one. Reference levels are computed the same way: "
              "real vs real (real training against real test images), the training target of the nearest "
              "training input, the class's mean training image and a flat image of its mean colour.")
    page.para(f"Paper: {PAPER['citation']}: {PAPER['note']}.", "note")
    if score_summary.get("ms_ssim", "computed") != "computed":
        page.para(f"MS-SSIM {score_summary['ms_ssim']}.", "note")
    metrics["ssim"] = {}
    for number, direction in (("I", "v2t"), ("II", "t2v")):
        if by_class is None or direction not in set(by_class["direction"]):
            continue
        set_table, aligned = ssim_tables(by_class, direction)
        name = "visual to tactile (seeing to feel)" if direction == "v2t" else "tactile to visual (touching to see)"
        page.table(set_table, f"Table {number}: {direction.upper()}, {name}: set-to-set Colour-SSIM per class")
        if aligned is not None:
            page.table(aligned, f"Table {number}b: {direction.upper()}: aligned scores against each output's "
                                f"own ground truth")
        else:
            page.para(f"{direction.upper()}: no output has an aligned ground truth (pairs are by class only, "
                      f"as in ViTac), so only the set-to-set protocol applies.", "note")
        overall = by_class[(by_class["direction"] == direction) & (by_class["class"] == "(all)")]
        level = {}
        for row in overall.itertuples(index=False):
            key = candidate_label(row.candidate, row.scope)
            level[f"{key}_set"] = None if pd.isna(row.set_colour_ssim) else round(float(row.set_colour_ssim), 4)
            if not pd.isna(row.colour_ssim):
                level[f"{key}_aligned"] = round(float(row.colour_ssim), 4)
        metrics["ssim"][direction] = level
    if by_class is not None:
        scores_figure(by_class, figures / "scores.png")
        page.figure("figures/scores.png", "Colour-SSIM of generated images beside the reference levels, all classes")

    # -- image grids
    page.heading("Image grids")
    for direction in DIRECTIONS:
        table_path = layout["generated"] / direction / "generated.parquet"
        if table_path.is_file():
            grid = image_grid(pd.read_parquet(table_path), scores, direction)
            write_png(figures / f"grid_{direction}.png", grid)
            page.figure(f"figures/grid_{direction}.png",
                        f"{direction.upper()}: test inputs, generated outputs and ground truth (or the nearest real "
                        f"test image) per class")

    # -- Table III
    page.heading("Augmented classification (Table III)")
    tables = []
    metrics["classify"] = {}
    for modality in MODALITIES:
        summary = _read_json(layout["classify"] / modality / "summary.json")
        if summary is None:
            continue
        if summary.get("status", "ok") != "ok":
            page.para(f"{modality}: {summary['status']}", "note")
            metrics["classify"][modality] = {"status": summary["status"]}
            continue
        table = pd.read_parquet(layout["classify"] / modality / "accuracy.parquet")
        tables.append(table)
        page.table(accuracy_table(table, modality),
                   f"Table III ({modality}): test accuracy after each iteration, mean ± std over seeds "
                   f"{sorted(table['seed'].unique().tolist())}")
        last = table[table["epoch"] == table["epoch"].max()]
        entry = {s: round(float(g["test_accuracy"].mean()), 4) for s, g in last.groupby("setting")}
        gan = last[(last["setting"] == "real") & last["gan_test_accuracy"].notna()]
        if not gan.empty:
            entry["gan_test"] = round(float(gan["gan_test_accuracy"].mean()), 4)
        metrics["classify"][modality] = entry
    if tables:
        accuracy_figure(pd.concat(tables, ignore_index=True), figures / "classification.png")
        page.figure("figures/classification.png", "Test accuracy per iteration: real only, real + generated, "
                                                  "low-data settings and the GAN-test")
    else:
        page.para("No classification results found.")

    # -- timings
    page.heading("Stage timings")
    timings = stage_timings(layout["benchmarks"])
    if timings.empty:
        page.para("No Snakemake benchmark files under logs/benchmarks (the run was not made by Snakemake).")
    else:
        page.table(timings, "Wall time and peak memory of each job (Snakemake benchmark files, last run)")
        timing_figure(timings, figures / "timings.png")
        page.figure("figures/timings.png", "Wall seconds per job")
        metrics["seconds"] = {row.job: round(row.seconds, 2) for row in timings.itertuples(index=False)}

    title = "vtgen report" + (" (SYNTHETIC data)" if provenance["synthetic"] else "")
    document = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>" + "\n".join(page.html)
                + "</body></html>\n")
    (build / "index.html").write_text(document)
    (build / "summary.md").write_text(f"# {title}\n\n" + "\n".join(page.md))
    (build / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    count = len(list(figures.glob("*.png")))
    _publish(build, out_dir)
    print(f"report: {out_dir / 'index.html'}, {out_dir / 'summary.md'}, {out_dir / 'metrics.json'} and "
          f"{count} figures in {out_dir / 'figures'}")
    return metrics


def _publish(build: Path, out_dir: Path) -> None:
    """Move the finished report from ``build`` into ``out_dir``: the figures folder by one rename,
    each file by an atomic replace (other files in ``out_dir``, such as its README, are kept)."""
    old = out_dir / ".figures.old"
    shutil.rmtree(old, ignore_errors=True)
    if (out_dir / "figures").exists():
        (out_dir / "figures").rename(old)
    (build / "figures").rename(out_dir / "figures")
    for name in ("metrics.json", "summary.md", "index.html"):
        (build / name).replace(out_dir / name)
    shutil.rmtree(old, ignore_errors=True)
    shutil.rmtree(build, ignore_errors=True)
