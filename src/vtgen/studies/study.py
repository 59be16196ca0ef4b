"""Study runs outside the main job: the paper's experiment matrix and the speed-accuracy trade.

A *variant* is the default configuration with dotted-key overrides applied (the study's ``base``
first, then the variant's own), e.g. ``{"preset.batch_size": 8}``; ``preset.`` is
short for ``presets.<translation.preset>.``. ``run_variant`` runs the real stage functions on
it - data stages again only when the variant changes a data section, then train, generate and
score per direction - and adds a GAN-test: a texture classifier trained on the run's real
training tiles of the target modality, applied to the generated test images.

* ``studies.experiments.runs``: named rows of the paper (per-class models, network settings, noise,
  the paired-dataset round trip). Standard rows can also be queued as DVC experiments
  (``vtgen experiments --queue``): the same overrides become ``dvc exp run -S key=value``.
* ``studies.tradeoff.settings``: settings x seeds of one direction; ``summarise_tradeoff`` gives quality
  (aligned Colour-SSIM, else set-to-set) against seconds (train + generate), marks the Pareto
  frontier and makes the per-class ``capacity: auto`` choice: for each class the cheapest
  setting whose quality is within ``studies.capacity.tolerance`` of that class's best.

Intermediate files of a run (tiles, checkpoints, models, generated images) live under
``studies_work/<kind>/<name>/``; the run's result folder holds only small tables and
``result.json`` and is written atomically.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from vtgen.io.timing import read_with_times
from vtgen.io.params import model_settings, resolve_key, set_keys, validate_params
from vtgen.io.provenance import code_fingerprint
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS

DATA_SECTIONS = ("dataset", "synthetic", "ingest", "roi", "pairing")
WORK_ROOT = Path("studies_work")
MODES = ("standard", "round_trip", "per_class")


# ---------------------------------------------------------------- overrides

def apply_overrides(params: dict, overrides: dict) -> dict:
    """A validated deep copy of ``params`` with each dotted key of ``overrides`` replaced.

    Only existing keys can be set (a typo is an error naming the key), and the result must pass
    the params schema.
    """
    return validate_params(set_keys(params, overrides), source=f"params with overrides {overrides}")


def variant_overrides(params: dict, kind: str, name: str) -> dict:
    """``studies.<kind>.base`` followed by the overrides of experiment run or trade-off setting ``name``."""
    if kind not in ("experiments", "tradeoff"):
        raise ValueError(f"unknown study kind '{kind}' (experiments | tradeoff)")
    study = params["studies"][kind]
    table = study["runs"] if kind == "experiments" else study["settings"]
    if name not in table:
        raise ValueError(f"studies.{kind}: nothing named '{name}' (defined: {', '.join(table)})")
    own = table[name]["set"] if kind == "experiments" else table[name]
    return {**study["base"], **own}


def is_default(params: dict, variant: dict) -> bool:
    """Whether ``variant`` trains the main job's model on the main job's data (seeds and generation aside)."""
    def key(p: dict) -> str:
        run = {k: v for k, v in p["translation"].items()
               if k not in ("seed", "scope", "threads", "log_every", "checkpoint_every")}
        return json.dumps([run, model_settings(p), *(p[s] for s in DATA_SECTIONS)], sort_keys=True)
    return key(params) == key(variant)


def dvc_queue_command(params: dict, name: str) -> list[str] | None:
    """``dvc exp run --queue -n <name> -S key=value ...`` for an experiment the main pipeline can run, else None."""
    experiment = params["studies"]["experiments"]["runs"][name]
    if experiment["mode"] != "standard":
        return None
    command = ["dvc", "exp", "run", "--queue", "-n", name]
    for key, value in variant_overrides(params, "experiments", name).items():
        command += ["-S", f"{resolve_key(params, key)}={json.dumps(value)}"]
    return command


# ---------------------------------------------------------------- one run

def prepare_data(params: dict, variant: dict, default_pairs: Path, work: Path) -> Path:
    """The pairs folder for ``variant``: the main job's when no data section changed, else fresh
    render/ingest/roi/pairs outputs under ``work/data``."""
    if all(variant[s] == params[s] for s in DATA_SECTIONS):
        return default_pairs
    from vtgen.stages.ingest import run_ingest
    from vtgen.stages.pairs import run_pairing
    from vtgen.stages.render import render_dataset
    from vtgen.stages.roi import run_roi

    data = work / "data"
    raw = Path(variant["dataset"]["path"])
    if variant["dataset"]["source"] == "synthetic":
        cfg = variant["synthetic"]
        raw = data / "raw"
        if not (raw / "summary.json").is_file():
            render_dataset(raw, cfg["classes"], cfg["samples_per_class"], cfg["size"], cfg["aligned"], cfg["seed"],
                           workers=cfg["workers"])
    workers = variant["ingest"]["workers"]
    if not (data / "pairs" / "splits.parquet").is_file():
        run_ingest(raw, variant["dataset"], data / "ingest", workers)
        run_roi(data / "ingest" / "manifest.parquet", variant["roi"], data / "roi", workers)
        run_pairing(data / "roi" / "tiles.parquet", variant["pairing"], data / "pairs")
    return data / "pairs"


_JUDGES: dict = {}


def gan_test(variant: dict, splits: pd.DataFrame, generated: pd.DataFrame, modality: str) -> dict:
    """Accuracy of a classifier trained on the real training tiles of ``modality`` (classify settings, the
    paired list's first seed) on the real test tiles and on the generated test images ("GAN-test"). The classifier
    is trained once per process for the same tiles and settings."""
    from vtgen.core.classifier import accuracy, train_classifier
    from vtgen.io.images import read_tiles
    from vtgen.stages.classify import classify_seeds

    cfg = variant["classify"]
    real = splits[splits["modality"] == modality]
    train = real[real["split"] == "train"].sort_values("path")
    classes = sorted(train["class"].unique())
    if len(classes) < 2:
        return {"gan_test": None, "real_test": None, "note": f"not applicable: {len(classes)} class"}
    label = {c: i for i, c in enumerate(classes)}
    test = real[(real["split"] == "test") & real["class"].isin(classes)].sort_values("path")
    fake = generated[(generated["split"] == "test") & generated["class"].isin(classes)].sort_values("output_path")

    def load(frame: pd.DataFrame, column: str):
        return (read_tiles(list(frame[column]), cfg["size"]),
                torch.tensor([label[c] for c in frame["class"]], dtype=torch.long))

    key = json.dumps([list(train["path"]), list(test["path"]), cfg], sort_keys=True, default=str)
    if key not in _JUDGES:
        test_x, test_y = load(test, "path")
        seed = classify_seeds(cfg["seeds"], None)[0][0]  # the studies render aligned data: the paired list
        run = train_classifier(*load(train, "path"), test_x, test_y, len(classes), cfg, seed)
        _JUDGES[key] = (run.model, run.test_accuracy[-1])
    model, real_accuracy = _JUDGES[key]
    fake_x, fake_y = load(fake, "output_path")
    return {"gan_test": accuracy(model, fake_x, fake_y) if len(fake_x) else None, "real_test": real_accuracy, "note": ""}


def _quality(by_class: pd.DataFrame) -> pd.DataFrame:
    """Per class (and ``(all)``) quality of the generated images: aligned Colour-SSIM where there is a
    ground truth, else set-to-set Colour-SSIM; with the reference levels beside it."""
    rows = []
    for cls, group in by_class.groupby("class", sort=True):
        levels = {r.candidate: r for r in group.itertuples()}
        gen = levels.get("generated")
        if gen is None:
            continue
        aligned = not pd.isna(gen.colour_ssim)
        metric = "colour_ssim" if aligned else "set_colour_ssim"
        row = {"class": cls, "metric": "aligned" if aligned else "set-to-set", "quality": getattr(gen, metric),
               "set_colour_ssim": gen.set_colour_ssim}
        for ref in ("real_train", "nearest_neighbour", "mean_image", "flat_mean_colour"):
            row[ref] = getattr(levels[ref], "set_colour_ssim" if ref == "real_train" else metric) if ref in levels else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def run_direction(variant: dict, direction: str, pairs_dir: Path, work: Path, label: str,
                  progress: bool = True) -> tuple[pd.DataFrame, dict]:
    """Train every ``translation.scope`` entry of ``direction``, generate and score: (quality table, timings;
    ``trained`` gives each scope's width and steps as trained, which capacity auto may choose)."""
    from vtgen.stages.generate import run_generate
    from vtgen.stages.score import by_class, score_direction
    from vtgen.stages.train import run_train

    timings = {"train_seconds": 0.0, "trained": {}}
    for scope in variant["translation"]["scope"]:
        summary = run_train(variant, direction, scope, pairs_dir, work / "models" / direction / scope,
                            checkpoint_root=work / "checkpoints", progress=progress) \
            if not (work / "models" / direction / scope / "train.json").is_file() \
            else read_with_times(work / "models" / direction / scope / "train.json")
        timings["train_seconds"] += summary["wall_seconds"]
        timings["trained"][scope] = {"width": summary["settings"]["ngf"], "steps": summary["steps"],
                                     "capacity": summary.get("capacity", {}).get("mode", "fixed")}
    started = time.perf_counter()
    run_generate(variant, direction, pairs_dir, work / "models" / direction, work / "generated" / direction,
                 progress=progress)
    timings["generate_seconds"] = round(time.perf_counter() - started, 2)
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table")
    pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"the {direction} pair table")
    generated = pd.read_parquet(work / "generated" / direction / "generated.parquet")
    scores = score_direction(direction, generated, splits, pairs, variant["score"]["batch_size"])
    quality = _quality(by_class(scores))
    judged = gan_test(variant, splits, generated, DIRECTIONS[direction][1])
    quality.insert(0, "direction", direction)
    quality.insert(0, "run", label)
    return quality, {**timings, "gan_test": judged["gan_test"], "judge_real_test": judged["real_test"]}


def work_folder(kind: str, name: str, variant: dict) -> Path:
    """``studies_work/<kind>/<name>/<key>``: the key is SHA-256 of the resolved params and of the code the study
    runs (``code_fingerprint("vtgen.studies.study")``, which covers the stages it calls), so neither a changed
    variant nor changed code ever reuses a model or tile trained by another."""
    key = json.dumps({"params": variant, "code": code_fingerprint("vtgen.studies.study")}, sort_keys=True)
    return WORK_ROOT / kind / name / hashlib.sha256(key.encode()).hexdigest()[:12]


def run_variant(params: dict, kind: str, name: str, out_dir: str | Path, pairs_dir: str | Path = "data/pairs",
                capacity: str | Path | None = None, progress: bool = True) -> dict:
    """Stage entry: run experiment or trade-off setting ``name`` and write ``out_dir`` atomically.

    ``out_dir`` gets ``quality.csv`` (per run, direction and class: quality and reference levels)
    and ``result.json`` (overrides, seconds, GAN-test, headline quality). A trade-off setting runs
    once per ``studies.tradeoff.seeds`` entry; ``per_class`` experiments read the capacity choice
    written by ``vtgen frontier`` (``capacity``).
    """
    overrides = variant_overrides(params, kind, name)
    variant = apply_overrides(params, overrides)
    work = work_folder(kind, name, variant)
    pairs_dir = prepare_data(params, variant, Path(pairs_dir), work)
    if kind == "tradeoff":
        tradeoff = params["studies"]["tradeoff"]
        runs = [(f"seed{seed}", apply_overrides(variant, {"translation.seed": seed, "generate.seed": seed}),
                 [tradeoff["direction"]], "standard") for seed in tradeoff["seeds"]]
    else:
        experiment = params["studies"]["experiments"]["runs"][name]
        runs = [("run", variant, experiment["directions"], experiment["mode"])]
    from vtgen.io.provenance import code_version

    tables, result = [], {"kind": kind, "name": name, "overrides": overrides, "code": code_version(),
                          "synthetic": variant["dataset"]["source"] == "synthetic",
                          "size": model_settings(variant)["size"], "runs": {}}
    result["is_default"] = is_default(params, variant)
    if kind == "experiments":
        experiment = params["studies"]["experiments"]["runs"][name]
        result.update(about=experiment["about"], paper=experiment["paper"], mode=experiment["mode"])
    for label, run_params, directions, mode in runs:
        run_work = work / label
        if mode == "per_class":
            quality, info = run_per_class(run_params, pairs_dir, run_work, capacity, progress)
        elif mode == "round_trip":
            quality, info = run_round_trip(run_params, pairs_dir, run_work, progress)
        else:
            quality, info = [], {}
            for direction in directions:
                table, timing = run_direction(run_params, direction, pairs_dir, run_work / direction, label, progress)
                quality.append(table)
                info[direction] = timing
            quality = pd.concat(quality, ignore_index=True)
        quality["run"] = label
        tables.append(quality)
        result["runs"][label] = info
    quality = pd.concat(tables, ignore_index=True)
    overall = quality[quality["class"] == "(all)"]
    result["quality"] = {d: {"mean": float(g["quality"].mean()), "std": float(g["quality"].std(ddof=0)),
                             "metric": g["metric"].iloc[0]} for d, g in overall.groupby("direction")}
    with atomic_output_dir(out_dir) as tmp:
        quality.to_csv(tmp / "quality.csv", index=False, float_format="%.6f")
        (tmp / "result.json").write_text(json.dumps(result, indent=2, default=_jsonable) + "\n")
    print(f"study {kind}/{name}: " + ", ".join(f"{d} quality {q['mean']:.3f} ({q['metric']})"
                                               for d, q in result["quality"].items()) + f" -> {out_dir}")
    return result


def _jsonable(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value)}")


# ---------------------------------------------------------------- special experiments

def run_per_class(variant: dict, pairs_dir: Path, work: Path, capacity: str | Path | None,
                  progress: bool = True) -> tuple[pd.DataFrame, dict]:
    """One V2T model per class (the paper's cloth-type rows). With a capacity table (``capacity.json``
    from ``vtgen frontier``) each class trains at its chosen setting; without one, at the variant's."""
    classes = sorted(read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table")["class"].unique())
    choice = json.loads(Path(capacity, "capacity.json").read_text()) if capacity else None
    tables, info = [], {"classes": {}}
    for cls in classes:
        overrides = {"translation.scope": [cls]}
        setting = "fixed"
        if choice:
            if cls not in choice["classes"]:
                raise ValueError(f"{capacity}: capacity.json has no choice for class '{cls}'")
            setting = choice["classes"][cls]["setting"]
            overrides.update(choice["settings"][setting])
        run_params = apply_overrides(variant, overrides)
        table, timing = run_direction(run_params, "v2t", pairs_dir, work / cls / setting, "run", progress)
        tables.append(table[table["class"] == cls])
        info["classes"][cls] = {"setting": setting, **timing}
    quality = pd.concat(tables, ignore_index=True)
    overall = quality.drop(columns=["class"]).mean(numeric_only=True).to_dict()
    quality = pd.concat([quality, pd.DataFrame([{**overall, "class": "(all)", "direction": "v2t", "run": "run",
                                                  "metric": quality["metric"].iloc[0]}])], ignore_index=True)
    info["train_seconds"] = round(sum(c["train_seconds"] for c in info["classes"].values()), 2)
    if choice:
        info["fixed_large"] = {"setting": choice["large"], "train_seconds_estimate":
                               round(choice["large_seconds"] * len(classes), 2)}
    return quality, info


def run_round_trip(variant: dict, pairs_dir: Path, work: Path, progress: bool = True) -> tuple[pd.DataFrame, dict]:
    """The paired-dataset run: train V2T, then T2V twice - on real pairs only, and on real pairs mixed
    50/50 with (generated tactile -> original visual) pairs - and score each round trip
    visual -> tactile -> visual against the original visual test image (aligned Colour-SSIM)."""
    from vtgen.io.checkpoints import load_translator
    from vtgen.stages.generate import translate
    from vtgen.core.metrics import colour_ssim
    from vtgen.io.images import read_tiles

    _, v2t_info = run_direction(variant, "v2t", pairs_dir, work / "v2t", "run", progress)
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table")
    generated = pd.read_parquet(work / "v2t" / "generated" / "v2t" / "generated.parquet")
    real_t2v = read_table(pairs_dir / "t2v.parquet", PAIR_COLUMNS, "the t2v pair table")
    made = generated[generated["split"] == "train"]
    if made.empty:
        raise ValueError("round_trip needs generated training images: set generate.train_share > 0 in the experiment")
    real_train = real_t2v[real_t2v["split"] == "train"]
    keep = real_train.sample(n=min(len(real_train), len(made)), random_state=variant["translation"]["seed"])
    generated_pairs = pd.DataFrame({
        "direction": "t2v", "split": "train", "class": made["class"].to_numpy(),
        "input_path": made["output_path"].to_numpy(), "target_path": made["input_path"].to_numpy(),
        "input_source": "generated", "target_source": "generated", "aligned": True, "pair_kind": "pixel"})
    mixed_pairs = pd.concat([real_t2v[real_t2v["split"] != "train"], keep, generated_pairs], ignore_index=True)
    mixed_dir = work / "mixed_pairs"
    mixed_dir.mkdir(parents=True, exist_ok=True)
    mixed_pairs[PAIR_COLUMNS].to_parquet(mixed_dir / "t2v.parquet", index=False)
    shutil.copy(pairs_dir / "splits.parquet", mixed_dir / "splits.parquet")

    v2t_model, meta = load_translator(work / "v2t" / "models" / "v2t" / "all")
    test = splits[(splits["split"] == "test") & (splits["modality"] == "visual")].sort_values("path")
    originals = read_tiles(list(test["path"]), meta["size"])
    classes = list(test["class"])
    tactile = translate(v2t_model, originals, conditioning=meta["conditioning"],
                        labels=meta["conditioning"].labels(classes))
    rows, info = [], {"v2t": v2t_info, "mixed_training_pairs": {"real": len(keep), "generated": len(made)}}
    for label, source in (("real pairs only", pairs_dir), ("50/50 real and generated", mixed_dir)):
        from vtgen.stages.train import run_train
        out = work / label.replace(" ", "_").replace("/", "-") / "model"
        if not (out / "train.json").is_file():
            run_train(variant, "t2v", "all", source, out, checkpoint_root=out.parent / "checkpoints", progress=progress)
        back_model, back_meta = load_translator(out)
        back = translate(back_model, tactile, conditioning=back_meta["conditioning"],
                         labels=back_meta["conditioning"].labels(classes))
        ssim = colour_ssim(back.permute(0, 2, 3, 1).numpy(), originals.permute(0, 2, 3, 1).numpy(), 255.0)
        info[label] = {"train_seconds": read_with_times(out / "train.json")["wall_seconds"]}
        for cls in sorted(test["class"].unique()):
            mask = (test["class"] == cls).to_numpy()
            rows.append({"direction": f"round trip, T2V on {label}", "class": cls, "metric": "round trip",
                         "quality": float(ssim[mask].mean())})
        rows.append({"direction": f"round trip, T2V on {label}", "class": "(all)", "metric": "round trip",
                     "quality": float(ssim.mean())})
    return pd.DataFrame(rows), info


# ---------------------------------------------------------------- trade-off summary and capacity

def pareto_front(seconds: np.ndarray, quality: np.ndarray) -> np.ndarray:
    """Boolean mask of the points no other point beats: none is at most as slow and at least as good
    with one of the two strictly better."""
    seconds, quality = np.asarray(seconds, float), np.asarray(quality, float)
    mask = np.ones(len(seconds), dtype=bool)
    for i in range(len(seconds)):
        better = (seconds <= seconds[i]) & (quality >= quality[i]) & ((seconds < seconds[i]) | (quality > quality[i]))
        mask[i] = not better.any()
    return mask


def choose_capacity(per_class: pd.DataFrame, seconds: pd.Series, tolerance: float) -> dict:
    """Per class: the cheapest setting whose quality is within ``tolerance`` of the class's best.

    ``per_class`` has one row per setting and one column per class (mean quality over seeds);
    ``seconds`` is the setting's mean time. Such a setting is always on the class's own frontier:
    anything cheaper and at least as good would also be within tolerance.
    """
    choice = {}
    for cls in per_class.columns:
        best = per_class[cls].max()
        eligible = per_class.index[per_class[cls] >= best - tolerance]
        pick = min(eligible, key=lambda s: (seconds[s], -per_class.at[s, cls]))
        choice[cls] = {"setting": pick, "quality": float(per_class.at[pick, cls]), "best": float(best),
                       "best_setting": str(per_class[cls].idxmax()), "seconds": float(seconds[pick])}
    return choice


def summarise_tradeoff(params: dict, runs_root: str | Path, out_dir: str | Path) -> dict:
    """Stage entry (``vtgen frontier``): read every trade-off result under ``runs_root`` and write
    ``frontier.csv`` (one row per setting: seconds, quality and GAN-test mean and std over seeds,
    on_frontier, is_default), ``per_class.csv``, ``capacity.json``, ``pareto.png`` and the DVC
    plot series ``all_settings.csv``, ``pareto_frontier.csv``, ``main_default.csv``."""
    studies = params["studies"]
    settings = studies["tradeoff"]["settings"]
    rows, per_class = [], {}
    for name in settings:
        folder = Path(runs_root) / name
        result = json.loads((folder / "result.json").read_text())
        quality = pd.read_csv(folder / "quality.csv")
        per_seed = []
        for seed, info in result["runs"].items():
            timing = info[studies["tradeoff"]["direction"]]
            q = quality[(quality["run"] == seed) & (quality["class"] == "(all)")]["quality"].iloc[0]
            per_seed.append((timing["train_seconds"] + timing["generate_seconds"], q, timing["gan_test"]))
        seconds, qual, gan = (np.array(v, dtype=float) for v in zip(*per_seed))
        data_changed = any(resolve_key(params, k).split(".")[0] in DATA_SECTIONS
                           for k in variant_overrides(params, "tradeoff", name))
        rows.append({"setting": name, "overrides": json.dumps(settings[name]), "seeds": len(per_seed),
                     "seconds": seconds.mean(), "seconds_std": seconds.std(), "quality": qual.mean(),
                     "quality_std": qual.std(), "gan_test": np.nanmean(gan) if np.isfinite(gan).any() else math.nan,
                     "gan_test_std": np.nanstd(gan) if np.isfinite(gan).any() else math.nan,
                     "metric": quality["metric"].iloc[0], "size": result["size"], "changes_data": data_changed})
        per_class[name] = quality[quality["class"] != "(all)"].groupby("class")["quality"].mean()
    table = pd.DataFrame(rows)
    table["on_frontier"] = pareto_front(table["seconds"], table["quality"])
    table["is_default"] = [json.loads((Path(runs_root) / n / "result.json").read_text())["is_default"]
                           for n in table["setting"]]
    classes = pd.DataFrame(per_class).T
    same_data = table.loc[~table["changes_data"], "setting"]
    seconds = table.set_index("setting")["seconds"]
    tolerance = studies["capacity"]["tolerance"]
    choice = choose_capacity(classes.loc[list(same_data)], seconds, tolerance)
    overall = table.set_index("setting").loc[list(same_data), "quality"]
    large = str(overall.idxmax())
    capacity = {"tolerance": tolerance, "large": large, "large_seconds": float(seconds[large]),
                "settings": {n: variant_overrides(params, "tradeoff", n) for n in same_data}, "classes": choice,
                "seconds_auto": float(sum(c["seconds"] for c in choice.values())),
                "seconds_fixed_large": float(seconds[large] * len(choice))}
    capacity["saved_fraction"] = 1 - capacity["seconds_auto"] / capacity["seconds_fixed_large"]
    with atomic_output_dir(out_dir) as tmp:
        table.to_csv(tmp / "frontier.csv", index=False, float_format="%.6f")
        points = table[["setting", "seconds", "quality"]]  # the three series of the DVC plot `speed_accuracy`
        points.to_csv(tmp / "all_settings.csv", index=False, float_format="%.6f")
        points[table["on_frontier"]].sort_values("seconds").to_csv(tmp / "pareto_frontier.csv", index=False,
                                                                    float_format="%.6f")
        points[table["is_default"]].to_csv(tmp / "main_default.csv", index=False, float_format="%.6f")
        classes.rename_axis("setting").to_csv(tmp / "per_class.csv", float_format="%.6f")
        (tmp / "capacity.json").write_text(json.dumps(capacity, indent=2) + "\n")
        pareto_figure(table, tmp / "pareto.png", synthetic=params["dataset"]["source"] == "synthetic")
    print(f"frontier: {int(table['on_frontier'].sum())} of {len(table)} settings on the frontier; capacity auto "
          f"{capacity['seconds_auto']:.0f} s vs fixed '{large}' {capacity['seconds_fixed_large']:.0f} s "
          f"({100 * capacity['saved_fraction']:.0f}% saved) -> {out_dir}")
    return capacity


def pareto_figure(table: pd.DataFrame, path: Path, synthetic: bool) -> None:
    """Quality against seconds, one point per setting with its seed spread; frontier line; default ringed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.8))
    ax.errorbar(table["seconds"], table["quality"], xerr=table["seconds_std"], yerr=table["quality_std"],
                fmt="o", color="tab:blue", ecolor="0.6", capsize=3, label="setting (mean ± std over seeds)")
    front = table[table["on_frontier"]].sort_values("seconds")
    ax.step(front["seconds"], front["quality"], where="post", color="tab:orange", lw=2, label="Pareto frontier")
    for row in table.itertuples():
        ax.annotate(row.setting, (row.seconds, row.quality), textcoords="offset points", xytext=(5, 4), fontsize=8)
    default = table[table["is_default"]]
    ax.scatter(default["seconds"], default["quality"], s=220, facecolors="none", edgecolors="red", lw=2,
               label="default", zorder=5)
    ax.set_xscale("log")
    ax.set_xlabel("seconds per model (train + generate), log scale")
    ax.set_ylabel(f"Colour-SSIM ({table['metric'].iloc[0]})")
    ax.set_title("Speed-accuracy trade" + (" - SYNTHETIC data" if synthetic else ""))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
