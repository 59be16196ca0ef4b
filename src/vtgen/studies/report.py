"""Studies report: ``reports/studies/index.html`` (+ ``summary.md``, ``figures/``).

Rendered from the templates ``studies.html`` / ``studies.md`` (on the same base template and helper as
the run's report, :mod:`vtgen.io.report_pages`). Sections: the paper's experiment rows (our numbers beside the reference levels and the paper's),
one section per experiment, the speed-accuracy trade (frontier table, Pareto plot, what more
compute buys), capacity auto per class, and the stability edge cases. Reads only the folders
named on the command line.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pandas as pd

from vtgen.io.report_pages import read_json, render_page, table_view
from vtgen.studies.study import variant_overrides

REFERENCES = {"real_train": "real vs real (set)", "nearest_neighbour": "nearest neighbour",
              "mean_image": "mean image", "flat_mean_colour": "flat colour"}


def _experiment_rows(params: dict, experiments_dir: Path) -> tuple[pd.DataFrame, dict]:
    """One row per experiment and direction: quality, reference levels, GAN-test, seconds, paper."""
    rows, details = [], {}
    for name, spec in params["studies"]["experiments"]["runs"].items():
        folder = experiments_dir / name
        result = read_json(folder / "result.json")
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


def _capacity_saving(run: dict) -> dict | None:
    """A per-class experiment's training time against the fixed large setting for every class."""
    if "fixed_large" not in run:
        return None
    large = run["fixed_large"]["setting"]
    at_large = [v["train_seconds"] for v in run["classes"].values() if v["setting"] == large]
    if at_large:  # classes trained at the large setting in this same run: the fairest yardstick
        fixed = sum(at_large) / len(at_large) * len(run["classes"])
        basis = f"the mean time of the {len(at_large)} classes trained at it here"
    else:
        fixed, basis = run["fixed_large"]["train_seconds_estimate"], "its trade-off time"
    return {"seconds": run["train_seconds"], "classes": len(run["classes"]), "fixed": fixed, "large": large,
            "basis": basis, "saved_percent": 100 * (1 - run["train_seconds"] / fixed)}


def _experiment_view(params: dict, name: str, result: dict, quality: pd.DataFrame) -> dict:
    """One experiment's section: its overrides, per-class table and (per-class mode) the time saved."""
    run = result["runs"]["run"]
    view = {"name": name, "about": result.get("about", ""), "saving": None,
            "overrides": json.dumps(variant_overrides(params, "experiments", name))}
    if result.get("mode") == "per_class":
        per_class = pd.DataFrame([{"class": c, "setting": v["setting"], "train s": v["train_seconds"],
                                   "GAN-test": v["gan_test"]} for c, v in run["classes"].items()])
        per_class = per_class.merge(quality[["class", "quality", "mean_image", "flat_mean_colour"]], on="class")
        view["table"] = table_view(per_class, f"{name}: one V2T model per class at its capacity-auto setting")
        view["saving"] = _capacity_saving(run)
    else:
        shown = quality[[c for c in ["direction", "class", "metric", "quality", *REFERENCES] if c in quality]]
        view["table"] = table_view(shown.rename(columns=REFERENCES), f"{name}: per class")
    return view


def studies_context(params: dict, experiments_dir: Path, frontier_dir: Path, stability_dir: Path) -> dict:
    """Every number and table of the studies report, read from the three input folders."""
    studies, synthetic = params["studies"], params["dataset"]["source"] == "synthetic"
    table, details = _experiment_rows(params, experiments_dir)
    frontier = pd.read_csv(frontier_dir / "frontier.csv")
    shown = frontier[["setting", "overrides", "size", "seconds", "seconds_std", "quality", "quality_std", "gan_test",
                      "on_frontier", "is_default"]].sort_values("seconds")
    gains = _compute_gains(frontier)
    capacity = read_json(frontier_dir / "capacity.json")
    choice = pd.DataFrame([{"class": c, **v} for c, v in capacity["classes"].items()])
    return {
        "title": "vtgen studies" + (" (SYNTHETIC data)" if synthetic else ""), "synthetic": synthetic,
        "setup": {"experiments_base": json.dumps(studies["experiments"]["base"]),
                  "tradeoff_base": json.dumps(studies["tradeoff"]["base"]),
                  "direction": studies["tradeoff"]["direction"], "seeds": studies["tradeoff"]["seeds"]},
        "experiments": table_view(table, "Experiments: our numbers, reference levels and the paper's"),
        "details": [_experiment_view(params, n, r, q) for n, (r, q) in details.items()],
        "frontier": table_view(shown, f"Trade-off settings (mean and std over {len(studies['tradeoff']['seeds'])} seeds)"),
        "settings": len(frontier),
        "gains": None if gains.empty else table_view(gains, "What more compute buys, from the measured settings"),
        "capacity": {**{k: capacity[k] for k in ("tolerance", "seconds_auto", "seconds_fixed_large", "large")},
                     "saved_percent": 100 * capacity["saved_fraction"],
                     "table": table_view(choice, "Capacity-auto choice per class")},
        "stability": table_view(pd.read_csv(stability_dir / "stability.csv"), "Edge cases of the parameter space"),
    }


def run_studies_report(params: dict, experiments_dir: str | Path, frontier_dir: str | Path,
                       stability_dir: str | Path, out_dir: str | Path = "reports/studies") -> None:
    """Build the studies report (index.html, summary.md, figures/pareto.png) into ``out_dir``, written in a
    temporary sibling and then moved into place; reads only the three named folders."""
    experiments_dir, frontier_dir, stability_dir, out_dir = map(Path, (experiments_dir, frontier_dir, stability_dir,
                                                                        out_dir))
    context = studies_context(params, experiments_dir, frontier_dir, stability_dir)
    build = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(build, ignore_errors=True)
    (build / "figures").mkdir(parents=True)
    shutil.copyfile(frontier_dir / "pareto.png", build / "figures" / "pareto.png")
    page, summary = render_page("studies", context)
    (build / "index.html").write_text(page)
    (build / "summary.md").write_text(summary)
    old = out_dir.with_name(out_dir.name + ".old")
    shutil.rmtree(old, ignore_errors=True)
    if out_dir.exists():
        out_dir.rename(old)
    build.rename(out_dir)
    shutil.rmtree(old, ignore_errors=True)
    print(f"studies report: {out_dir / 'index.html'} ({len(context['details'])} experiments, {context['settings']} "
          f"trade-off settings, {len(context['stability']['rows'])} stability cases)")
