"""The report's figures: PNG files drawn with matplotlib (Agg) from the collected run data."""

from __future__ import annotations

import shutil
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from vtgen.core.domain import DIRECTIONS, MODALITIES  # noqa: E402
from vtgen.io.report_tables import settings_in, ssim_name  # noqa: E402
from vtgen.io.tables import candidate_label  # noqa: E402

FIGURES = ("losses", "scores", "grid_v2t", "grid_t2v", "nearest_v2t", "nearest_t2v", "classification", "timings")


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


def nearest_training_figure(nearest: pd.DataFrame, pictures: np.ndarray, direction: str, path: Path) -> None:
    """The score stage's ``nearest_training`` rows of ``direction`` with its picture strip (generated images in rank
    order on top, the training image nearest to each below): each pair with their distance, in red where the
    memorisation check flags it (nearer than any real held-out image)."""
    rows = nearest[nearest["direction"] == direction].sort_values("rank")
    side = pictures.shape[0] // 2
    fig, axes = plt.subplots(2, len(rows), figsize=(1.5 * len(rows) + 0.6, 3.7), squeeze=False)
    for column, (_, r) in enumerate(rows.iterrows()):
        flagged = bool(r["flagged"])
        for row, ax in enumerate((axes[0][column], axes[1][column])):
            ax.imshow(pictures[row * side:(row + 1) * side, column * side:(column + 1) * side])
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_xlabel(str(r["generated_class"] if row == 0 else r["train_class"]), fontsize=7)
            if flagged:
                for spine in ax.spines.values():
                    spine.set(color="tab:red", linewidth=2)
        axes[0][column].set_title(f"{r['distance']:.3g}" + (" flagged" if flagged else ""), fontsize=8,
                                  color="tab:red" if flagged else "black")
    axes[0][0].set_ylabel("generated", fontsize=8)
    axes[1][0].set_ylabel("nearest training", fontsize=8)
    first = rows.iloc[0]
    fig.suptitle(f"{direction.upper()}: generated test images nearest to a training image ({first['view']} view); "
                 f"real held-out images lie at {first['threshold']:.3g} or more", fontsize=9)
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
    for direction in DIRECTIONS:  # the memorisation check's nearest generated images beside their training images
        if direction in data["nearest_pictures"]:
            nearest_training_figure(data["nearest_training"], data["nearest_pictures"][direction], direction,
                                    figures / f"nearest_{direction}.png")
    tables = [e["accuracy"] for e in data["classify"].values() if not e["accuracy"].empty]
    if tables:
        accuracy_figure(pd.concat(tables, ignore_index=True), figures / "classification.png")
    if not data["timings"].empty:
        timing_figure(data["timings"], figures / "timings.png")
    return {name: (figures / f"{name}.png").is_file() for name in FIGURES}
