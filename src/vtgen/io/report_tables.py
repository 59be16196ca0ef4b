"""The report's tables: the run's scores, accuracies and models as DataFrames of text cells.

Every score is shown with its 95% interval and n; generated data is read against the best trivial
baseline or real data only when the intervals do not overlap ("within noise" otherwise). The paper's
printed values (:data:`vtgen.io.report_pages.PAPER`) stand beside this run's where the experiment
matches. :func:`vtgen.io.report_pages.table_view` turns a table into template data.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from vtgen.io.report_pages import PAPER, PAPER_ROWS, interval_cell, overlap, table_view
from vtgen.io.tables import candidate_label

SETTING_ORDER = ["real", "real+generated", "low-data real", "low-data real+generated"]
GAN_TEST = "GAN-test"
SSIM_BASELINES = ("nearest_neighbour", "mean_image", "flat_mean_colour")
DISTRIBUTION_BASELINES = ("nearest_neighbour", "mean_image", "flat_mean_colour", "blurred_real")
# (metric, view) columns of the distribution tables, in order; their labels
DISTRIBUTION_SHOWN = [("kid", "classifier"), ("kid_classwise", "classifier"), ("fid", "classifier"), ("two_sample", "classifier"),
                      ("precision", "classifier"), ("recall", "classifier"), ("coverage", "classifier"),
                      ("kid", "random"), ("fid", "random"), ("two_sample", "random"), ("spectrum", "pixels")]
METRIC_LABELS = {"kid": "KID", "kid_classwise": "class-wise KID", "fid": "FID", "two_sample": "two-sample acc.", "precision": "precision",
                 "recall": "recall", "density": "density", "coverage": "coverage", "spectrum": "spectrum dist."}


def settings_in(names) -> list[str]:
    """The settings among ``names`` in SETTING_ORDER, then any other (the policy's candidates) sorted."""
    present = set(names)
    return [s for s in SETTING_ORDER if s in present] + sorted(present - set(SETTING_ORDER) - {GAN_TEST})


def has_value(value) -> bool:
    """Whether ``value`` is neither None nor NaN (infinities count)."""
    return value is not None and not pd.isna(value)


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
    references = {c: r for c, r in references.items() if r is not None and has_value(r.get(metric))}
    if record is None or not references or not has_value(record.get(metric)):
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
            if metric != "ms_ssim" or any(r is not None and has_value(r.get(metric)) for r in generated):
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
    per_class = [r for scope, r in overall.items() if scope not in ("all", "-") and has_value(r.get("set_colour_ssim"))]
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
    """With against without generated images: both final accuracies with 95% intervals, the difference with
    its paired 95% interval and the classify stage's verdict ("within noise" when that interval includes 0)."""
    settings, n = summary.get("settings") or {}, (summary.get("counts") or {}).get("real_test", "—")
    rows = []
    for item in summary.get("comparisons") or []:
        a, b = settings.get(item["setting"], {}), settings.get(item["against"], {})
        rows.append({"setting": item["setting"],
                     "accuracy [95%]": interval_cell(a.get("final_mean"), *(a.get("interval") or (None, None))),
                     "against": item["against"],
                     "against: accuracy [95%]": interval_cell(b.get("final_mean"), *(b.get("interval") or (None, None))),
                     "difference [paired 95%]": f"{item['difference']:+.3f}" + (
                         " [{:+.3f}, {:+.3f}]".format(*item["paired_interval"]) if item.get("paired_interval") else ""),
                     "n test": n, "verdict": item["verdict"]})
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


def conditioning_cell(run: dict) -> str:
    """What a model was told (train.json ``conditioning``), marked ``(auto)`` where ``translation.conditioning``
    said auto and the objective chose it (train.json ``conditioning_setting``)."""
    kind = run.get("conditioning", "none")
    return f"{kind} (auto)" if run.get("conditioning_setting") == "auto" else kind


def models_table(runs: list[dict]) -> pd.DataFrame:
    """One row per model folder from its train.json (a direction without pairs: its status, no model)."""
    return pd.DataFrame([{
        "model": f"{r['direction']}/{r['scope']}", "status": r.get("status", "ok"), "preset": r.get("preset"),
        "conditioning": conditioning_cell(r) if r.get("status", "ok") == "ok" else None,
        "objective": (r.get("objective") or {}).get("name"), "objective chosen because": (r.get("objective") or {}).get("reason"),
        "capacity": (r.get("capacity") or {}).get("mode"), "width (ngf)": (r.get("settings") or {}).get("ngf"),
        "size": (r.get("settings") or {}).get("size"), "iterations": r.get("steps"),
        "generator kept": (r.get("selection") or {}).get("step"), "kept because": (r.get("selection") or {}).get("reason"),
        "wall s": r.get("wall_seconds"),
        "s/iteration": r.get("seconds_per_iteration"), "final val L1": r.get("final_val_l1"),
        "device": r.get("device"), "precision": r.get("precision"), "precision chosen because": r.get("precision_reason"),
    } for r in runs])


def capacity_table(runs: list[dict]) -> pd.DataFrame | None:
    """Per model trained with capacity auto and per class: the width it needed, the step it settled at (and the
    floor it had to reach, scored by recognition), and the model's compute against the fixed large model
    (train.json ``capacity``); None when no model used auto."""
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
                         "floor": choice.get("floor", ""),
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
               "and the step its validation score settled at (Colour-SSIM; for class pairs the judge's recognition, "
               "which settles only from its floor up); compute against the fixed large model")
