"""Studies report: ``reports/studies/index.html`` (+ ``summary.md``, ``figures/``).

Sections: the paper's experiment rows (our numbers beside the reference levels and the paper's),
one section per experiment, the speed-accuracy trade (frontier table, Pareto plot, what more
compute buys), capacity auto per class, and the stability edge cases. Reads only the folders
named on the command line.
"""

from __future__ import annotations

import html
import json
import shutil
from pathlib import Path

import pandas as pd

from vtgen.stages.report import _Page, PAPER, STYLE
from vtgen.studies.study import variant_overrides

REFERENCES = {"real_train": "real vs real (set)", "nearest_neighbour": "nearest neighbour",
              "mean_image": "mean image", "flat_mean_colour": "flat colour"}


def _experiment_rows(params: dict, experiments_dir: Path) -> tuple[pd.DataFrame, dict]:
    """One row per experiment and direction: quality, reference levels, GAN-test, seconds, paper."""
    rows, details = [], {}
    for name, spec in params["studies"]["experiments"]["runs"].items():
        folder = experiments_dir / name
        result = json.loads((folder / "result.json").read_text())
        quality = pd.read_csv(folder / "quality.csv")
        details[name] = (result, quality)
        for direction, group in quality.groupby("direction", sort=False):
            overall = group[group["class"] == "(all)"].iloc[0]
            timing = result["runs"]["run"].get(direction, result["runs"]["run"])
            row = {"experiment": name, "direction": direction, "metric": overall["metric"],
                   "generated": overall["quality"]}
            for key, label in REFERENCES.items():
                row[label] = overall.get(key, float("nan"))
            row["GAN-test"] = timing.get("gan_test") if isinstance(timing, dict) else None
            row["train s"] = timing.get("train_seconds") if isinstance(timing, dict) else None
            row["paper"] = spec["paper"]
            rows.append(row)
    return pd.DataFrame(rows), details


def _compute_gains(frontier: pd.DataFrame) -> pd.DataFrame:
    """For 1x, 2x, 10x and 100x the seconds of the study's base setting (the one with no overrides of
    its own, else the main job's): the best measured setting within that budget."""
    reference = frontier[frontier["overrides"] == "{}"]
    if reference.empty:
        reference = frontier[frontier["is_default"]]
    if reference.empty:
        return pd.DataFrame()
    base, base_quality = float(reference["seconds"].iloc[0]), float(reference["quality"].iloc[0])
    rows = []
    for factor in (1, 2, 10, 100):
        within = frontier[frontier["seconds"] <= factor * base * 1.05]
        best = within.loc[within["quality"].idxmax()]
        beyond = factor * base > frontier["seconds"].max() * 1.05
        rows.append({"budget": f"{factor}x {reference['setting'].iloc[0]} ({factor * base:.0f} s)",
                     "best measured setting": best["setting"], "Colour-SSIM": best["quality"],
                     "± seeds": best["quality_std"], f"gain over {reference['setting'].iloc[0]}": best["quality"] - base_quality,
                     "note": "more than the most expensive setting measured: no better setting is known" if beyond else ""})
    return pd.DataFrame(rows)


def run_studies_report(params: dict, experiments_dir: str | Path, frontier_dir: str | Path,
                       stability_dir: str | Path, out_dir: str | Path = "reports/studies") -> None:
    """Build the studies report into ``out_dir`` (written in a temporary sibling, then moved into place)."""
    experiments_dir, frontier_dir, stability_dir, out_dir = map(Path, (experiments_dir, frontier_dir, stability_dir, out_dir))
    build = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(build, ignore_errors=True)
    (build / "figures").mkdir(parents=True)
    page = _Page()
    synthetic = params["dataset"]["source"] == "synthetic"
    if synthetic:
        page.para("SYNTHETIC DATA: every number on this page comes from the embedded procedural ViTac-like dataset, "
                  "not from real visual or GelSight images.", "banner")
    studies = params["studies"]
    page.para(f"Experiments run at laptop scale: overrides {json.dumps(studies['experiments']['base'])} on every run; "
              f"trade-off settings on top of {json.dumps(studies['tradeoff']['base'])}, "
              f"{studies['tradeoff']['direction'].upper()}, seeds {studies['tradeoff']['seeds']}. "
              f"Paper: {PAPER['citation']}; {PAPER['note']}.", "note")

    # ---- experiments
    page.heading("The paper's experiments")
    table, details = _experiment_rows(params, experiments_dir)
    page.para("Quality is aligned Colour-SSIM where the test pairs are aligned views (each output against its own "
              "ground truth), else the paper's set-to-set Colour-SSIM. Reference levels are computed the same way "
              "for trivial candidates; real vs real is set-to-set. GAN-test: a classifier trained on the run's real "
              "training tiles of the target modality, applied to the generated test images.")
    page.table(table, "Experiments: our numbers, reference levels and the paper's")
    for name, (result, quality) in details.items():
        page.heading(name, 3)
        page.para(f"{result.get('about', '')}. Overrides: {json.dumps(variant_overrides(params, 'experiments', name))}.")
        run = result["runs"]["run"]
        if result.get("mode") == "per_class":
            per_class = pd.DataFrame([{"class": c, "setting": v["setting"], "train s": v["train_seconds"],
                                       "GAN-test": v["gan_test"]} for c, v in run["classes"].items()])
            per_class = per_class.merge(quality[["class", "quality", "mean_image", "flat_mean_colour"]], on="class")
            page.table(per_class, f"{name}: one V2T model per class at its capacity-auto setting")
            if "fixed_large" in run:
                large = run["fixed_large"]["setting"]
                at_large = [v["train_seconds"] for v in run["classes"].values() if v["setting"] == large]
                if at_large:  # classes trained at the large setting in this same run: the fairest yardstick
                    fixed = sum(at_large) / len(at_large) * len(run["classes"])
                    basis = f"the mean time of the {len(at_large)} classes trained at it here"
                else:
                    fixed, basis = run["fixed_large"]["train_seconds_estimate"], "its trade-off time"
                page.para(f"Training time with capacity auto: {run['train_seconds']:.0f} s for all "
                          f"{len(run['classes'])} classes, against about {fixed:.0f} s for the fixed setting "
                          f"'{large}' for every class ({basis} x {len(run['classes'])}): "
                          f"{100 * (1 - run['train_seconds'] / fixed):.0f}% saved.")
        else:
            shown = quality[[c for c in ["direction", "class", "metric", "quality", *REFERENCES] if c in quality]]
            page.table(shown.rename(columns=REFERENCES), f"{name}: per class")

    # ---- trade-off
    page.heading("Speed against accuracy")
    frontier = pd.read_csv(frontier_dir / "frontier.csv")
    shutil.copy(frontier_dir / "pareto.png", build / "figures" / "pareto.png")
    page.figure("figures/pareto.png", "Colour-SSIM against seconds per model (train + generate); orange: Pareto "
                "frontier; red ring: the main job's setting; bars: spread over seeds")
    shown = frontier[["setting", "overrides", "size", "seconds", "seconds_std", "quality", "quality_std", "gan_test",
                      "on_frontier", "is_default"]].sort_values("seconds")
    page.table(shown, f"Trade-off settings (mean and std over {len(studies['tradeoff']['seeds'])} seeds)")
    gains = _compute_gains(frontier)
    if not gains.empty:
        page.table(gains, "What more compute buys, from the measured settings")

    # ---- capacity auto
    capacity = json.loads((frontier_dir / "capacity.json").read_text())
    page.heading("Capacity auto: model only what a class needs")
    page.para(f"Per class, the cheapest trade-off setting whose Colour-SSIM (pooled model, that class's test images) "
              f"is within {capacity['tolerance']} of the class's best. Settings that change the tiles (resolution) "
              f"are left out, since per-class models share the main job's tiles.")
    choice = pd.DataFrame([{"class": c, **v} for c, v in capacity["classes"].items()])
    page.table(choice, "Capacity-auto choice per class")
    page.para(f"Estimated training time: {capacity['seconds_auto']:.0f} s with capacity auto, against "
              f"{capacity['seconds_fixed_large']:.0f} s for the fixed best-overall setting '{capacity['large']}' for "
              f"every class: {100 * capacity['saved_fraction']:.0f}% saved.")

    # ---- stability
    page.heading("Numerical stability at the edges")
    stability = pd.read_csv(stability_dir / "stability.csv")
    page.para("Each case trains through the real training loop; it either ends with finite weights and outputs or "
              "stops with the message shown. No case writes a model with non-finite weights.")
    page.table(stability, "Edge cases of the parameter space")

    title = "vtgen studies" + (" (SYNTHETIC data)" if synthetic else "")
    document = (f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>"
                f"<style>{STYLE}</style></head><body><h1>{html.escape(title)}</h1>"
                f"<p class=\"note\"><a href=\"../index.html\">main report</a></p>" + "\n".join(page.html)
                + "</body></html>\n")
    (build / "index.html").write_text(document)
    (build / "summary.md").write_text(f"# {title}\n\n" + "\n".join(page.md))
    old = out_dir.with_name(out_dir.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if out_dir.exists():
        out_dir.rename(old)
    build.rename(out_dir)
    shutil.rmtree(old, ignore_errors=True)
    print(f"studies report: {out_dir / 'index.html'} ({len(details)} experiments, {len(frontier)} trade-off settings, "
          f"{len(stability)} stability cases)")

