"""Classify stage: does adding generated images help a texture classifier? (the paper's Section V-C)

For one modality, an AlexNet-style classifier (:mod:`vtgen.classifier`) is trained once per
seed in each setting and its test accuracy recorded after every epoch:

* ``real`` - the real training tiles;
* ``real+generated`` - those plus every generated training image of the modality;
* ``low-data real`` - a per-class share ``classify.low_data_fraction`` of the real training tiles
  (at least one per class), one subset per seed, shared by both low-data settings;
* ``low-data real+generated`` - that subset plus every generated training image.

With ``classify.epoch_images: real`` (the default) an epoch is, in every setting, as many image
visits as the real training set holds (passes over a smaller set repeat, a larger one is sampled),
so every setting takes the same optimiser steps and a gain from generated images is not merely more
training: at 10% of the real images, 10 epochs of one pass each are a tenth of the steps, and more
steps alone lifted low-data accuracy more than the generated images did (benchmarks/README.md,
"Thirty-fifth round"). ``own`` is one pass over the setting's own images (the paper's protocol).
Beside generated images the real ones are repeated (:func:`real_repeats`) so that at least
``classify.real_share`` of a ``+generated`` setting's visits are real: pooled as they come, the low-data
real images were a tenth of the visits and the generated ones drowned them (benchmarks/README.md,
"Fortieth round"); summary.json's ``counts.real_repeats`` records the repeat per setting and seed.

Generated images of a modality come from the direction that produces it (tactile from v2t,
visual from t2v); all scope entries' images are used. Only rows generated from training inputs
enter training; the rows generated from test inputs form the GAN-test set, scored after every
epoch by the ``real`` classifiers (a real-only classifier applied to generated images). A
generated training row whose input is not a training tile is refused as a split leak. Without
generated training images the two ``+generated`` settings are skipped (noted in summary.json).
Test images always are the real test-split tiles.

The real validation-split tiles choose the *policy* (:mod:`vtgen.core.generated_policy`): which
generated images, if any, the default classifier adds. Each ``classify.policy.candidates`` entry
is one more setting (``real+generated`` itself where it keeps every generated image), trained
per seed; the candidate that beats ``real`` on the validation images beyond the 95% interval is
chosen, else real only. summary.json's ``policy`` records the choice, why, and its test accuracy
beside real only. Without validation images for every class (too few groups), or with
``mode: real``, no candidate is trained and the policy is real only, with the reason. With
``classify.patience`` > 0 every run stops early on the validation accuracy; ``classify.precision``
follows the same ``auto`` rule as training (bf16 only where the hardware computes it natively).

A classifier that learnt nothing is flagged, not hidden: an accuracy is *at chance* when chance,
1 / number of classes, lies inside the 95% Wilson score interval of that accuracy over the number
of images it was measured on (:func:`vtgen.core.classifier.at_chance`). The accuracy table's
``at_chance`` column applies the rule to each row's test accuracy; summary.json's ``at_chance`` per
setting applies it to the final-epoch accuracy averaged over seeds, on the real test images (the
seeds share those images, so they are not counted once per seed), and ``gan_test.at_chance`` to
the GAN-test's, on the generated test images. Each flagged setting prints one warning line. A
training loss that becomes non-finite stops the stage with a RuntimeError naming the modality,
setting, seed and epoch.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from tqdm import tqdm

from vtgen.core import generated_policy
from vtgen.core.classifier import TrainingDiverged, at_chance, class_probabilities, train_classifier, wilson_interval
from vtgen.core.confusion import confusion_counts
from vtgen.io.checkpoints import read_state_dict
from vtgen.io.classifiers import save_classifier
from vtgen.io.tables import GENERATED_COLUMNS, READ_SPLIT
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.core.domain import direction_producing, DIRECTIONS
from vtgen.io.tables import SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.core.device import resolve_device, resolve_precision

SETTINGS = ("real", "real+generated", "low-data real", "low-data real+generated")
ACCURACY_COLUMNS = {
    "modality": "object", "setting": "object", "seed": "int64", "epoch": "int64", "test_accuracy": "float64",
    "at_chance": "bool", "gan_test_accuracy": "float64", "val_accuracy": "float64", "train_images": "int64", "real_images": "int64", "generated_images": "int64",
    "seconds": "float64",
}
BY_CLASS_COLUMNS = ["modality", "setting", "class", "images", "accuracy", "low", "high", "seeds"]
# (with generated images, without): the paper's question, asked at full and at low data
COMPARISONS = (("real+generated", "real"), ("low-data real+generated", "low-data real"))
MORE_REAL = ("real", "low-data real")  # how much all real training images add over the low-data share
GAN_TEST = "GAN-test"
READ_GAN_TEST = "gan_test_read"  # the extra evaluation set of the test inputs told the class read from them


def check_generated_splits(generated: pd.DataFrame, splits: pd.DataFrame, direction: str) -> None:
    """Raise ValueError unless every generated ``train`` row comes from a training input tile and every
    ``test`` or ``test_read`` row (:data:`vtgen.io.tables.READ_SPLIT`) from a test input tile of the
    direction's source modality (no split leaks)."""
    source = DIRECTIONS[direction][0]
    tile_split = dict(zip(splits.loc[splits["modality"] == source, "path"],
                          splits.loc[splits["modality"] == source, "split"]))
    for split, needed in (("train", "train"), ("test", "test"), (READ_SPLIT, "test")):
        rows = generated[generated["split"] == split]
        found = rows["input_path"].map(tile_split)
        wrong = rows[found != needed]
        if len(wrong):
            first, actual = wrong.iloc[0], found[found != needed].iloc[0]
            where = "not a tile in splits.parquet" if pd.isna(actual) else f"a {actual}-split tile"
            kind = "split leak: " if split == "train" and actual == "test" else "inconsistent generated table: "
            raise ValueError(f"{kind}{len(wrong)} generated '{split}' image(s) of {direction} come from inputs that are "
                             f"not {needed}-split {source} tiles; first: {first['output_path']} from {first['input_path']} "
                             f"({where}); rerun the generate stage on these splits")


def read_gan_test(runs: dict, labels: torch.Tensor, num_classes: int) -> dict | None:
    """The GAN-test of the test inputs translated told the class read from each (``gan_read``, the generate
    stage's :data:`~vtgen.io.tables.READ_SPLIT`): the real-only classifiers' final-epoch accuracy on them
    against each input's true class, mean and std over seeds, with the Wilson 95% interval on their n and
    ``at_chance``. Issue 24's goal 3 for a generator told the class reads this one. None without such images."""
    if not len(labels):
        return None
    scores = [float((entry["run"].extra_predictions[READ_GAN_TEST] == labels).float().mean())
              for (setting, _), entry in sorted(runs.items()) if setting == "real"]
    mean, std = _mean_std(scores)
    return {"final_mean": mean, "final_std": std, "images": len(labels), "seeds": len(scores),
            "interval": _interval(mean, len(labels)), "at_chance": at_chance(mean, len(labels), num_classes)}


def low_data_subset(labels: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """Sorted indices of a per-class share ``fraction`` of ``labels`` (rounded, at least 1 per class), drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    chosen = []
    for label in np.unique(labels):
        members = np.flatnonzero(labels == label)
        keep = max(1, int(round(fraction * len(members))))
        chosen.append(rng.choice(members, size=keep, replace=False))
    return np.sort(np.concatenate(chosen)) if chosen else np.zeros(0, dtype=int)


def _mean_std(values) -> tuple[float | None, float | None]:
    """Mean and sample standard deviation (0 for one value) of the finite ``values``; None when there are none."""
    finite = [float(v) for v in values if v is not None and math.isfinite(v)]
    if not finite:
        return None, None
    return float(np.mean(finite)), float(np.std(finite, ddof=1)) if len(finite) > 1 else 0.0


def _finite_list(values) -> list[float | None]:
    """Floats for JSON: NaN (an empty test set) becomes None."""
    return [float(v) if math.isfinite(v) else None for v in values]


def summarise(table: pd.DataFrame, num_classes: int, test_images: int,
              gan_test_images: int = 0) -> tuple[dict, dict | None]:
    """Per setting: final-epoch accuracy mean/std over seeds, per-epoch means/stds and ``at_chance`` (the
    final mean on ``test_images`` images, see the module docstring); the same for the GAN-test (on
    ``gan_test_images``)."""
    per_setting, gan_test = {}, None
    present = set(table["setting"])
    for setting in [s for s in SETTINGS if s in present] + sorted(present - set(SETTINGS)):
        rows = table[table["setting"] == setting]
        by_epoch = rows.groupby("epoch")["test_accuracy"]
        final = final_rows(rows)
        mean, std = _mean_std(final["test_accuracy"])
        per_setting[setting] = {
            "final_mean": mean, "final_std": std, "seeds": int(final["seed"].nunique()),
            "epoch_mean": _finite_list(by_epoch.mean()),
            "epoch_std": _finite_list(by_epoch.std(ddof=1).fillna(0.0)),
            "train_images": int(final["train_images"].iloc[0]), "generated_images": int(final["generated_images"].iloc[0]),
            "epochs": [int(e) for e in final["epoch"]],
            "at_chance": at_chance(mean, test_images, num_classes) if mean is not None else False,
            "test_images": test_images, "interval": _interval(mean, test_images),
        }
        if rows["gan_test_accuracy"].notna().any():
            gan = rows.groupby("epoch")["gan_test_accuracy"]
            mean, std = _mean_std(final["gan_test_accuracy"])
            gan_test = {"setting": setting, "final_mean": mean, "final_std": std, "images": gan_test_images,
                        "interval": _interval(mean, gan_test_images),
                        "at_chance": at_chance(mean, gan_test_images, num_classes) if mean is not None else False,
                        "epoch_mean": _finite_list(gan.mean()),
                        "epoch_std": _finite_list(gan.std(ddof=1).fillna(0.0))}
    return per_setting, gan_test


def final_rows(table: pd.DataFrame) -> pd.DataFrame:
    """The last epoch's row of each (setting, seed) run: runs stopped early end before ``classify.epochs``."""
    return table.loc[table.groupby(["setting", "seed"])["epoch"].idxmax()].sort_values(["setting", "seed"])


def _interval(accuracy: float | None, count: int) -> list[float] | None:
    """The 95% Wilson interval of ``accuracy`` on ``count`` images (seeds share the test images, so they
    are not counted once per seed); None when nothing was measured."""
    if accuracy is None or count <= 0:
        return None
    return [round(v, 6) for v in wilson_interval(accuracy, count)]


def accuracy_by_class(predictions: dict[tuple[str, int], np.ndarray], labels: np.ndarray, classes: list[str],
                      modality: str) -> pd.DataFrame:
    """Final-epoch accuracy per setting and class (BY_CLASS_COLUMNS), with ``images`` (n) and the 95% Wilson
    interval; one ``(all)`` row per setting. ``predictions[(setting, seed)]`` are the predicted labels of the
    images whose true labels are ``labels``; the accuracy is the mean over seeds."""
    rows = []
    for setting in dict.fromkeys(name for name, _ in predictions):
        runs = [p for (name, _), p in predictions.items() if name == setting]
        groups = [(name, labels == i) for i, name in enumerate(classes)] + [("(all)", np.ones(len(labels), bool))]
        for name, rows_of in groups:
            n = int(rows_of.sum())
            if n == 0:
                continue
            value = float(np.mean([(p[rows_of] == labels[rows_of]).mean() for p in runs]))
            low, high = wilson_interval(value, n)
            rows.append({"modality": modality, "setting": setting, "class": name, "images": n, "accuracy": value,
                         "low": low, "high": high, "seeds": len(runs)})
    return pd.DataFrame(rows, columns=BY_CLASS_COLUMNS)


def _test_correct(runs: dict, sets: dict, setting: str, seeds: list[int]) -> np.ndarray:
    """``seeds x test images``: whether the run of ``setting`` with each seed read each real test image right."""
    test_y = sets["test"][1].numpy()
    return np.stack([runs[(setting, seed)]["run"].test_predictions.numpy() == test_y for seed in seeds])


def paired_gains(runs: dict, sets: dict) -> dict[tuple[str, str], tuple[float, float, float]]:
    """Each COMPARISONS pair's gain on the real test images, and MORE_REAL's (all real images against the low-data
    share), paired image by image over the seeds, with its 95% interval
    (:func:`vtgen.core.generated_policy.paired_difference`: split groups as units, the seeds' spread counted)."""
    seeds = sorted({seed for setting, seed in runs if setting == "real"})
    result = {}
    for better, against in COMPARISONS + (MORE_REAL,):
        if len(sets["test"][1]) and all((name, seed) in runs for name in (better, against) for seed in seeds):
            result[(better, against)] = generated_policy.paired_difference(
                _test_correct(runs, sets, better, seeds), _test_correct(runs, sets, against, seeds),
                sets["test_groups"])
    return result


def _paired_fields(gain: tuple[float, float, float] | None) -> dict | None:
    """A gain from :func:`paired_gains` as summary.json writes it: ``paired_interval`` (95%, rounded) and
    ``within_noise`` (the interval includes 0); None without a finite interval."""
    if gain is None or not math.isfinite(gain[1]):
        return None
    return {"paired_interval": [round(gain[1], 6), round(gain[2], 6)], "within_noise": gain[1] <= 0 <= gain[2]}


def compare_settings(per_setting: dict, paired: dict) -> list[dict]:
    """With vs without generated images (COMPARISONS): the difference of final mean accuracies, the paired
    difference's 95% interval (``paired``, from :func:`paired_gains`; both settings are scored on the same test
    images), ``within_noise`` where it includes 0, a verdict that ranks them only where it does not, and whether
    their separate Wilson intervals overlap (kept as data: that test needs a far larger gain)."""
    result = []
    for with_generated, without in COMPARISONS:
        a, b = per_setting.get(with_generated), per_setting.get(without)
        fields = _paired_fields(paired.get((with_generated, without)))
        if not a or not b or a["interval"] is None or b["interval"] is None or fields is None:
            continue
        difference = a["final_mean"] - b["final_mean"]
        result.append({
            "setting": with_generated, "against": without, "difference": round(difference, 6),
            "overlap": a["interval"][0] <= b["interval"][1] and b["interval"][0] <= a["interval"][1], **fields,
            "verdict": ("within noise (the paired 95% interval includes 0)" if fields["within_noise"]
                        else "generated images help" if difference > 0 else "generated images hurt")})
    return result


def more_real_data(paired: dict) -> dict | None:
    """summary.json's ``more_real_data``: all real training images against the low-data share (MORE_REAL), the
    paired test gain and its 95% interval, and ``within_noise`` where the interval includes 0 (then generated
    images learned from those same images have little room to help the low-data setting beyond the noise)."""
    fields = _paired_fields(paired.get(MORE_REAL))
    if fields is None:
        return None
    return {"setting": MORE_REAL[0], "against": MORE_REAL[1], "difference": round(paired[MORE_REAL][0], 6), **fields}


def chance_warnings(modality: str, summary: dict) -> list[str]:
    """One warning line per setting (and GAN-test) that summary.json flags ``at_chance``."""
    chance, cfg, counts = summary["chance"], summary["params"], summary["counts"]
    lines = []
    for setting, stats in summary["settings"].items():
        if stats["at_chance"]:
            lines.append(f"classify {modality}: warning: '{setting}' ended at chance level (accuracy "
                         f"{stats['final_mean']:.2f} on {counts['real_test']} test images, chance {chance:.2f}); "
                         f"check classify.lr ({cfg['lr']:g}), classify.epochs ({cfg['epochs']}) and the training images")
    gan = summary.get("gan_test")
    if gan and gan["at_chance"]:
        lines.append(f"classify {modality}: warning: GAN-test ('{gan['setting']}' classifier on generated test images) "
                     f"ended at chance level (accuracy {gan['final_mean']:.2f} on {gan['images']} generated test images, "
                     f"chance {chance:.2f}); the generated images may not show their class, or the '{gan['setting']}' "
                     f"classifier is at chance too")
    return lines


def plot_curves(path: Path, modality: str, per_setting: dict, gan_test: dict | None, message: str | None = None) -> None:
    """Test accuracy against epoch: mean line and a band of ± one standard deviation over seeds per setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(7, 4.5), dpi=110)
    if message:
        axes.text(0.5, 0.5, message, ha="center", va="center", wrap=True, transform=axes.transAxes)
        axes.set_axis_off()
    else:
        curves = [(name, stats, "-") for name, stats in per_setting.items()]
        if gan_test:
            curves.append(("GAN-test (real classifier on generated test images)", gan_test, "--"))
        for name, stats, style in curves:
            epochs = np.arange(1, len(stats["epoch_mean"]) + 1)
            mean = np.asarray(stats["epoch_mean"], dtype=float)
            std = np.asarray(stats["epoch_std"], dtype=float)
            line, = axes.plot(epochs, mean, style, marker="o", markersize=3, label=name)
            axes.fill_between(epochs, mean - std, mean + std, color=line.get_color(), alpha=0.2)
        axes.set_xlabel("epoch")
        axes.set_ylabel("test accuracy")
        axes.set_ylim(0, 1.02)
        axes.grid(alpha=0.3)
        axes.legend(fontsize=8, loc="lower right")
    axes.set_title(f"{modality} texture classification (mean ± std over seeds)")
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)


def _write_outputs(tmp: Path, table: pd.DataFrame, summary: dict, per_setting: dict, gan_test: dict | None,
                   message: str | None, by_class: pd.DataFrame | None = None) -> None:
    table = table.astype(ACCURACY_COLUMNS)[list(ACCURACY_COLUMNS)]
    table.to_parquet(tmp / "accuracy.parquet", index=False)
    table.to_csv(tmp / "accuracy.csv", index=False)
    by_class = pd.DataFrame(columns=BY_CLASS_COLUMNS) if by_class is None else by_class
    by_class.to_parquet(tmp / "by_class.parquet", index=False)
    by_class.to_csv(tmp / "by_class.csv", index=False, float_format="%.6f")
    (tmp / "summary.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    plot_curves(tmp / "curves.png", summary["modality"], per_setting, gan_test, message)


def classify_seeds(seeds: list[int] | dict, data_kind: dict | None) -> tuple[list[int], str]:
    """``classify.seeds`` as the classify stage runs them, and why: a list as set; a mapping gives its
    ``class_pairs`` list when every training pair is a class pair (``data_kind`` of the pairs summary), else its
    ``paired`` list (also without a pairs summary)."""
    if isinstance(seeds, list):
        return seeds, "as set"
    if data_kind is None:
        return seeds["paired"], "no pairs summary, so the paired list"
    if data_kind.get("class_pairs_only"):
        return seeds["class_pairs"], "every training pair is a class pair"
    return seeds["paired"], "some training pairs are pixel or name pairs"


def pairs_data_kind(pairs_dir: Path) -> dict | None:
    """The pairs stage's ``data_kind`` (pairs_dir/summary.json), or None where the folder has no summary."""
    path = pairs_dir / "summary.json"
    return json.loads(path.read_text()).get("data_kind") if path.is_file() else None


def run_classify(params: dict, modality: str, pairs_dir: str | Path, generated_root: str | Path, out_dir: str | Path,
                 progress: bool = True) -> dict:
    """Stage entry: train and test the classifiers of ``modality``; write ``out_dir`` atomically.

    Reads ``pairs_dir/splits.parquet`` and ``generated_root/<direction>/generated.parquet`` (paths in
    them relative to the working directory). Writes accuracy.parquet and accuracy.csv (one row per
    setting, seed and epoch; columns ACCURACY_COLUMNS, gan_test_accuracy NaN outside ``real``,
    val_accuracy NaN without validation images), summary.json (with ``chance`` and an ``at_chance``
    flag per setting and for the GAN-test, see the module docstring, ``real_confusion``: the real-only
    classifiers' confusion on the real test images, mean over seeds, rows true class and columns predicted in
    ``classes`` order, ``policy``: the generated images
    the default adds, chosen on the validation split, and its test accuracy beside real only,
    ``precision`` and ``throughput``: training and evaluation images per second) and curves.png;
    prints a warning line per flagged setting. A non-finite training loss raises RuntimeError naming
    modality, setting, seed and epoch. With fewer than 2 classes nothing is trained: the tables are
    empty and summary.json's ``status`` says why; otherwise ``status`` is "ok". The seeds are ``classify.seeds``
    as :func:`classify_seeds` reads them for the pairs summary's ``data_kind`` (summary.json's
    ``seeds``: the list and why).
    """
    pairs_dir, generated_root, out_dir = Path(pairs_dir), Path(generated_root), Path(out_dir)
    seeds, seeds_why = classify_seeds(params["classify"]["seeds"], pairs_data_kind(pairs_dir))
    cfg = dict(params["classify"], seeds=seeds)
    torch.set_num_threads(cfg["threads"])
    direction = direction_producing(modality)
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    generated_file = generated_root / direction / "generated.parquet"
    generated = read_table(generated_file, GENERATED_COLUMNS,
                           f"the {direction} output table of the generate stage ({modality} images)")
    check_generated_splits(generated, splits, direction)
    real = splits[splits["modality"] == modality]
    classes = sorted(real[real["split"] == "train"]["class"].unique())
    summary: dict = {"modality": modality, "direction": direction, "classes": classes, "params": dict(cfg),
                     "seeds": {"seeds": seeds, "why": seeds_why}, "weights": cfg["weights"] or None, "notes": []}
    if len(classes) < 2:
        return _not_applicable(summary, modality, len(real[real["split"] == "train"]), out_dir)
    sets = _image_sets(real, generated, classes, cfg["size"], direction, summary["notes"])
    settings, skipped = _applicable_settings(sets, modality, generated_file, summary["notes"])
    plan = policy_plan(cfg["policy"], sets, classes, settings)
    settings += [c["setting"] for c in plan["candidates"] if c["setting"] not in settings]
    device = resolve_device(params["translation"]["device"])
    precision, why = resolve_precision(cfg["precision"], device)
    runs, speed = _train_settings(sets, settings, plan, cfg, modality, len(classes), device, precision, progress)
    table = accuracy_rows(runs, modality, len(classes), len(sets["test"][0]))
    predictions = {k: r["run"].test_predictions.numpy() for k, r in runs.items()}
    predictions.update({(GAN_TEST, seed): r["run"].extra_predictions["gan_test"].numpy()
                        for (setting, seed), r in runs.items() if setting == "real" and len(sets["gan"][0])})
    per_setting, gan_test = summarise(table, len(classes), len(sets["test"][0]), len(sets["gan"][0]))
    gan_test_read = read_gan_test(runs, sets["gan_read"][1], len(classes))
    paired = paired_gains(runs, sets)
    by_class = pd.concat([
        accuracy_by_class({k: v for k, v in predictions.items() if k[0] != GAN_TEST}, sets["test"][1].numpy(), classes,
                          modality),
        accuracy_by_class({k: v for k, v in predictions.items() if k[0] == GAN_TEST}, sets["gan"][1].numpy(), classes,
                          modality)], ignore_index=True)
    real_confusion = confusion_counts([p for (setting, _), p in predictions.items() if setting == "real"],
                                      sets["test"][1].numpy(), len(classes))
    encoder = runs[("real", cfg["seeds"][0])]["run"].model
    summary.update(status="ok", chance=1.0 / len(classes), device=str(device), precision={"used": precision, "why": why},
                   counts=sets["counts"], settings=per_setting, skipped=skipped, gan_test=gan_test,
                   **({"gan_test_read": gan_test_read} if gan_test_read else {}),
                   comparisons=compare_settings(per_setting, paired), more_real_data=more_real_data(paired),
                   policy=choose_policy(plan, runs, sets, per_setting),
                   real_confusion=[[round(float(v), 6) for v in row] for row in real_confusion],
                   test_images_per_class=sets["counts"]["per_class_real_test"],
                   encoder={"file": "encoder.pt", "setting": "real", "seed": cfg["seeds"][0]},
                   wall_seconds=round(float(table.groupby(["setting", "seed"])["seconds"].first().sum()), 2),
                   throughput=speed)
    with atomic_output_dir(out_dir) as tmp:
        _write_outputs(tmp, table, summary, per_setting, gan_test, None, by_class)
        save_classifier(tmp / "encoder.pt", encoder, classes,
                        {"modality": modality, "setting": "real", "seed": cfg["seeds"][0],
                         "final_test_accuracy": per_setting["real"]["final_mean"]})
    _print_result(summary, modality, len(cfg["seeds"]), out_dir)
    return summary


def _not_applicable(summary: dict, modality: str, real_train: int, out_dir: Path) -> dict:
    """Fewer than 2 classes: empty tables and a status saying why."""
    classes = summary["classes"]
    held = f" ({classes[0]})" if classes else ""
    status = f"not applicable: classification needs at least 2 classes, the data has {len(classes)}{held}"
    summary.update(status=status, chance=None, counts={"real_train": real_train}, settings={}, skipped={},
                   gan_test=None, comparisons=[], more_real_data=None, policy=None)
    with atomic_output_dir(out_dir) as tmp:
        _write_outputs(tmp, pd.DataFrame(columns=list(ACCURACY_COLUMNS)), summary, {}, None, status)
    print(f"classify {modality}: warning: {status}; empty tables -> {out_dir}")
    return summary


def _image_sets(real: pd.DataFrame, generated: pd.DataFrame, classes: list[str], size: int, direction: str,
                notes: list[str]) -> dict:
    """The image sets as (images, labels): ``train``, ``val`` and ``test`` (real), ``generated`` (training
    inputs translated), ``gan`` (test inputs translated, for the GAN-test) and ``gan_read`` (test inputs
    translated told the class read from them, where the generate stage wrote them; else empty), plus ``counts`` and the
    split groups of the validation and test images (``val_groups``, ``test_groups``). Each tile is
    decoded once here and shared by every setting and seed. Images of classes without real training
    tiles are left out, with a note; a test or validation image in a training set is a split leak and
    an error."""
    label_of = {name: i for i, name in enumerate(classes)}
    by_split = {split: real[real["split"] == split].sort_values("path") for split in ("train", "val", "test")}
    gen_train = generated[generated["split"] == "train"].sort_values(["scope", "output_path"])
    gen_test = generated[generated["split"] == "test"].sort_values(["scope", "output_path"])
    gen_read = generated[generated["split"] == READ_SPLIT].sort_values(["scope", "output_path"])
    for name, frame in (("real validation", by_split["val"]), ("real test", by_split["test"]),
                        ("generated training", gen_train), ("generated test", gen_test)):
        unknown = sorted(set(frame["class"]) - set(classes))
        if unknown:
            notes.append(f"{name} images of classes without real training tiles left out: {', '.join(unknown)}")
    real_val, real_test, gen_train, gen_test, gen_read = (
        f[f["class"].isin(classes)] for f in (by_split["val"], by_split["test"], gen_train, gen_test, gen_read))
    real_train = by_split["train"]
    held_out = set(real[real["split"].isin(["test", "val"])]["path"])
    leaked = held_out & (set(real_train["path"]) | set(gen_train["output_path"]))
    if leaked:  # check_generated_splits has vetted the inputs; this guards the assembled sets themselves
        raise ValueError(f"split leak: {len(leaked)} held-out image(s) in the training set, e.g. {sorted(leaked)[0]}")

    def load(frame: pd.DataFrame, column: str) -> tuple[torch.Tensor, torch.Tensor]:
        remedy = "rerun the roi stage" if column == "path" else f"rerun the generate stage ({direction})"
        return (read_tiles(list(frame[column]), size, remedy=remedy),
                torch.tensor([label_of[c] for c in frame["class"]], dtype=torch.long))

    sets = {"train": load(real_train, "path"), "val": load(real_val, "path"), "test": load(real_test, "path"),
            "generated": load(gen_train, "output_path"), "gan": load(gen_test, "output_path"),
            "gan_read": load(gen_read, "output_path"),
            "val_groups": real_val["group"].astype(str).to_numpy(), "test_groups": real_test["group"].astype(str).to_numpy(),
            "val_classes": sorted(set(real_val["class"]))}
    sets["counts"] = {"real_train": len(real_train), "real_val": len(real_val), "real_test": len(real_test),
                      "generated_train": len(gen_train), "generated_test": len(gen_test),
                      "per_class_real_train": real_train["class"].value_counts().sort_index().to_dict(),
                      "per_class_real_test": {c: int((real_test["class"] == c).sum()) for c in classes},
                      "low_data_real_train": {}, "real_repeats": {}}
    return sets


def _applicable_settings(sets: dict, modality: str, generated_file: Path, notes: list[str]) -> tuple[list[str], dict]:
    """The settings that can run (``+generated`` ones need generated training images) and why others cannot."""
    skipped, settings = {}, list(SETTINGS)
    if len(sets["generated"][0]) == 0:
        reason = f"no generated training images of {modality} in {generated_file} (generate.train_share is 0?)"
        skipped = {s: reason for s in SETTINGS if s.endswith("+generated")}
        settings = [s for s in SETTINGS if s not in skipped]
    if len(sets["gan"][0]) == 0:
        notes.append(f"no generated test images of {modality}: no GAN-test")
    if len(sets["test"][0]) == 0:
        notes.append(f"no real test tiles of {modality}: test accuracy is NaN")
    return settings, skipped


# ---------------------------------------------------------------- the policy: which generated images the default adds


def policy_plan(policy: dict, sets: dict, classes: list[str], settings: list[str]) -> dict:
    """The candidates to train (classify.policy), or none and the reason the policy is real only: mode
    ``real``, no generated training images, or classes without validation images. A candidate that
    keeps every generated image is the ``real+generated`` setting, trained anyway."""
    plan = {"mode": policy["mode"], "confidence": policy["confidence"], "candidates": [], "fallback": None}
    if policy["mode"] == "real":
        plan["fallback"] = "classify.policy.mode is real: generated images are never added"
    elif "real+generated" not in settings:
        plan["fallback"] = "no generated training images to add"
    else:
        plan["fallback"] = generated_policy.missing_validation(sets["val_classes"], classes)
    if plan["fallback"]:
        return plan
    gen_y, train_y = sets["generated"][1].numpy(), sets["train"][1].numpy()
    real_per_class = {int(c): int(n) for c, n in zip(*np.unique(train_y, return_counts=True))}
    for item in policy["candidates"]:
        ratio, kind = float(item["ratio"]), item["filter"]
        keeps_all = kind == "all" and all(n <= math.floor(ratio * real_per_class.get(int(c), 0) + 1e-9)
                                          for c, n in zip(*np.unique(gen_y, return_counts=True)))
        name = "real+generated" if keeps_all else generated_policy.candidate_setting(ratio, kind)
        if name not in [c["setting"] for c in plan["candidates"]]:
            plan["candidates"].append({"setting": name, "ratio": ratio, "filter": kind,
                                       "real_per_class": real_per_class})
    return plan


def choose_policy(plan: dict, runs: dict, sets: dict, per_setting: dict) -> dict:
    """summary.json's ``policy``: the setting chosen on the validation split (or real only and why), each
    candidate's validation accuracy and gain, and the chosen setting's test accuracy beside real only,
    with 95% Wilson intervals and the paired test gain's interval over test groups."""
    seeds = sorted({seed for setting, seed in runs if setting == "real"})
    result = {"mode": plan["mode"], "val_images": int(len(sets["val"][0])),
              "val_groups": int(len(set(sets["val_groups"])))}
    if plan["fallback"]:
        result.update(chosen="real", reason=plan["fallback"], candidates=[])
    else:
        val_y = sets["val"][1].numpy()
        correct = {name: np.stack([runs[(name, s)]["run"].extra_predictions["val"].numpy() == val_y for s in seeds])
                   for name in ["real"] + [c["setting"] for c in plan["candidates"]]}
        result.update(generated_policy.choose(correct, sets["val_groups"]))
        for row, item in zip(result["candidates"], plan["candidates"]):
            row.update(ratio=item["ratio"], filter=item["filter"],
                       generated_images=[int(runs[(item["setting"], s)]["generated"]) for s in seeds])
    chosen, real = per_setting.get(result["chosen"]) or {}, per_setting.get("real") or {}
    test_y = sets["test"][1].numpy()
    gain = generated_policy.paired_difference(
        _test_correct(runs, sets, result["chosen"], seeds), _test_correct(runs, sets, "real", seeds),
        sets["test_groups"]) if len(test_y) else (None, None, None)
    result["uses_generated"] = result["chosen"] != "real"
    result["test"] = {"setting": result["chosen"], "accuracy": chosen.get("final_mean"),
                      "interval": chosen.get("interval"), "real_accuracy": real.get("final_mean"),
                      "real_interval": real.get("interval"), "images": int(len(test_y)),
                      "gain": None if gain[0] is None else round(gain[0], 6),
                      "gain_interval": None if gain[0] is None else [round(gain[1], 6), round(gain[2], 6)]}
    return result


# ---------------------------------------------------------------- training every setting and seed


def real_repeats(real: int, generated: int, share: float) -> int:
    """How often each of ``real`` images is visited per pass beside ``generated`` ones so that at least ``share`` of
    the visits are real: ``max(1, ceil(share / (1 - share) * generated / real))``; 1 for ``share`` 0 or no
    generated image (``classify.real_share``)."""
    if share <= 0 or generated == 0 or real == 0:
        return 1
    return max(1, math.ceil(share / (1 - share) * generated / real - 1e-9))


def _training_set(setting: str, seed: int, sets: dict, subset: torch.Tensor, plan: dict, real_model,
                  real_share: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, int, int]:
    """The training images and labels of ``setting`` for ``seed`` (the real ones repeated :func:`real_repeats`
    times beside generated ones), how many distinct real images they hold and the repeat count."""
    (train_x, train_y), (gen_x, gen_y) = sets["train"], sets["generated"]
    real_x, real_y = (train_x[subset], train_y[subset]) if setting.startswith("low-data") else (train_x, train_y)
    if setting in ("real+generated", "low-data real+generated"):
        chosen = torch.arange(len(gen_x))
    elif setting in ("real", "low-data real"):
        chosen = torch.zeros(0, dtype=torch.long)
    else:
        item = next(c for c in plan["candidates"] if c["setting"] == setting)
        probability = None
        if item["filter"] == "confident":
            probability = class_probabilities(real_model, gen_x)[torch.arange(len(gen_y)), gen_y].numpy()
        chosen = torch.from_numpy(generated_policy.generated_subset(
            gen_y.numpy(), item["real_per_class"], item["ratio"], item["filter"], seed, probability,
            plan["confidence"]))
    repeats = real_repeats(len(real_x), len(chosen), real_share)
    return (torch.cat([real_x.repeat(repeats, 1, 1, 1), gen_x[chosen]]),
            torch.cat([real_y.repeat(repeats), gen_y[chosen]]), len(real_x), repeats)


def _train_settings(sets: dict, settings: list[str], plan: dict, cfg: dict, modality: str, num_classes: int, device,
                    precision: str, progress: bool) -> tuple[dict, dict]:
    """Train one classifier per seed and setting (``real`` first: the confident filter reads its model).
    Returns ``{(setting, seed): {"run", "train_images", "real_images", "generated"}}`` and summary.json's
    ``throughput`` (:func:`throughput`). A candidate whose filter keeps no generated image is the
    ``real`` run itself (the same images and seed train the same model).

    On the CPU, ``classify.threads`` > 1 trains the seeds in that many worker processes of one torch thread each
    (at most one per seed; threads left over go to each worker's torch): every seed's runs are then the runs of
    one thread, so the results do not depend on how many workers there were."""
    weights_file = cfg["weights"] or None
    if weights_file and not Path(weights_file).is_file():
        raise ValueError(f"{weights_file}: weights file not found (classify.weights; \"\" trains from scratch)")
    job = dict(sets=sets, settings=settings, plan=plan, cfg=cfg, modality=modality, num_classes=num_classes,
               device=device, precision=precision, weights=read_state_dict(weights_file) if weights_file else None)
    workers = min(cfg["threads"], len(cfg["seeds"])) if device.type == "cpu" else 1
    bar = tqdm(total=len(settings) * len(cfg["seeds"]), desc=f"classify {modality}", unit="run", disable=not progress,
               dynamic_ncols=True)
    if workers == 1:
        done = [_seed_runs(seed, job, bar) for seed in cfg["seeds"]]
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        bar.set_description(f"classify {modality}: {len(cfg['seeds'])} seeds in {workers} processes")
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
                                 initargs=(_to_bytes(job), cfg["threads"] // workers)) as pool:
            futures = [pool.submit(_worker_seed_runs, seed) for seed in cfg["seeds"]]
            done = []
            try:
                for future in futures:  # in seed order, so the tables and counts are written as one process would
                    done.append(_from_bytes(future.result()))
                    bar.update(len(settings))
            finally:  # a seed's error cancels the seeds not started (the shutdown's cancel: vtgen.io.images._stream)
                pool.shutdown(wait=True, cancel_futures=True)
    bar.close()
    runs: dict = {}
    work = dict.fromkeys(_WORK_KEYS, 0)
    for seed, (seed_runs, counts, seed_work) in zip(cfg["seeds"], done):
        runs.update(seed_runs)
        sets["counts"]["low_data_real_train"][str(seed)] = counts["low_data_real_train"]
        for setting, repeats in counts["real_repeats"].items():
            sets["counts"]["real_repeats"].setdefault(setting, {})[str(seed)] = repeats
        for name, value in seed_work.items():
            work[name] += value
    return runs, throughput(work)


_WORKER_JOB: dict = {}
# the throughput sums of a job's runs: images and seconds of training, of the normalisation pass and of evaluation
_WORK_KEYS = ("train", "train_seconds", "norm_seconds", "eval", "eval_seconds")


def _to_bytes(value) -> bytes:
    """``value`` as torch.save bytes: tensors cross the process pipe as plain bytes, never through /dev/shm (a
    container's may hold 64 MB)."""
    import io

    buffer = io.BytesIO()
    torch.save(value, buffer)
    return buffer.getvalue()


def _from_bytes(data: bytes):
    import io

    return torch.load(io.BytesIO(data), weights_only=False)  # written by this stage's own worker


def _start_worker(job: bytes, threads: int) -> None:
    """A seed worker's start: one torch thread (or the threads left over), and the job's images and settings."""
    torch.set_num_threads(max(1, threads))
    _WORKER_JOB.update(_from_bytes(job))


def _worker_seed_runs(seed: int) -> bytes:
    return _to_bytes(_seed_runs(seed, _WORKER_JOB, tqdm(disable=True)))


def _seed_runs(seed: int, job: dict, bar) -> tuple[dict, dict, dict]:
    """Every setting's run of one seed: ``({(setting, seed): entry}, counts, work)``, where ``counts`` holds the
    seed's low-data size and real repeats per setting and ``work`` the throughput sums of its runs."""
    sets, cfg, modality = job["sets"], job["cfg"], job["modality"]
    val = sets["val"] if len(sets["val"][0]) else None
    runs: dict = {}
    counts: dict = {"real_repeats": {}}
    work = dict.fromkeys(_WORK_KEYS, 0)
    subset = torch.from_numpy(low_data_subset(sets["train"][1].numpy(), cfg["low_data_fraction"], seed))
    counts["low_data_real_train"] = len(subset)
    for setting in job["settings"]:
        real_run = runs.get(("real", seed), {}).get("run")
        x, y, real_count, repeats = _training_set(setting, seed, sets, subset, job["plan"], real_run and real_run.model,
                                                  cfg["real_share"])
        generated = len(x) - real_count * repeats
        if generated:
            counts["real_repeats"][setting] = repeats
        bar.set_description(f"classify {modality}: {setting}, seed {seed}")
        if setting not in SETTINGS and not generated:
            runs[(setting, seed)] = dict(runs[("real", seed)], generated=0, seconds=0.0)
            bar.update(1)
            continue
        extra = None
        if setting == "real":
            extra = {name: sets[key] for name, key in (("gan_test", "gan"), (READ_GAN_TEST, "gan_read"))
                     if len(sets[key][0])} or None
        run = _train_one(x, y, sets, cfg, modality, setting, seed, job["num_classes"], job["device"], job["precision"],
                         job["weights"], cfg["weights"] or None, extra, val, bar)
        runs[(setting, seed)] = {"run": run, "train_images": real_count + generated, "real_images": real_count,
                                 "generated": generated}
        for name, value in zip(_WORK_KEYS, (run.train_images, run.train_seconds, run.norm_seconds, run.eval_images,
                                            run.eval_seconds)):
            work[name] += value
        bar.update(1)
    return runs, counts, work


def _train_one(x, y, sets, cfg, modality, setting, seed, num_classes, device, precision, weights, weights_file, extra,
               val, bar):
    """One :func:`train_classifier` run; a diverged loss becomes a RuntimeError naming the setting and seed."""
    def show(epoch: int, row: dict) -> None:
        bar.set_postfix({"epoch": epoch, "acc": f"{row['test_accuracy']:.3f}", "loss": f"{row['train_loss']:.3f}"},
                        refresh=True)

    epoch_images = len(sets["train"][0]) if cfg["epoch_images"] == "real" else None
    try:
        return train_classifier(x, y, *sets["test"], num_classes, cfg, seed, device, extra_eval=extra, weights=weights,
                                weights_source=str(weights_file), retrain_layers=cfg["retrain_layers"], progress=show,
                                val=val, precision=precision, epoch_images=epoch_images)
    except TrainingDiverged as exc:
        bar.close()
        raise RuntimeError(f"classify {modality}: setting '{setting}', seed {seed}: the training loss became "
                           f"non-finite ({exc.loss}) in epoch {exc.epoch}; lower classify.lr "
                           f"(now {cfg['lr']:g})") from exc


def accuracy_rows(runs: dict, modality: str, num_classes: int, test_images: int) -> pd.DataFrame:
    """The accuracy table (ACCURACY_COLUMNS): one row per setting, seed and epoch run."""
    rows = []
    for (setting, seed), entry in runs.items():
        run = entry["run"]
        nan = [math.nan] * len(run.test_accuracy)
        for epoch, (acc, gan_acc, val_acc) in enumerate(zip(run.test_accuracy, run.extra_accuracy.get("gan_test", nan),
                                                            run.extra_accuracy.get("val", nan)), start=1):
            rows.append({"modality": modality, "setting": setting, "seed": seed, "epoch": epoch,
                         "test_accuracy": acc, "at_chance": at_chance(acc, test_images, num_classes),
                         "gan_test_accuracy": gan_acc if setting == "real" else math.nan, "val_accuracy": val_acc,
                         "train_images": entry["train_images"], "real_images": entry["real_images"],
                         "generated_images": entry["generated"], "seconds": entry.get("seconds", run.seconds)})
    return pd.DataFrame(rows, columns=list(ACCURACY_COLUMNS))


def throughput(work: dict) -> dict:
    """summary.json's ``throughput``: training image visits (all settings, seeds, epochs) and their seconds of
    mini-batch training, images classified in the per-epoch evaluations (test and GAN-test sets) and their
    seconds, the seconds of the per-epoch batch-norm refresh, and the images per second of each."""
    def rate(images, seconds):
        return round(images / seconds, 1) if seconds > 0 else None

    return {"train_images": int(work["train"]), "train_seconds": round(work["train_seconds"], 4),
            "train_images_per_second": rate(work["train"], work["train_seconds"]),
            "eval_images": int(work["eval"]), "eval_seconds": round(work["eval_seconds"], 4),
            "eval_images_per_second": rate(work["eval"], work["eval_seconds"]),
            "norm_refresh_seconds": round(work["norm_seconds"], 4)}


def _print_result(summary: dict, modality: str, seeds: int, out_dir: Path) -> None:
    per_setting, gan_test = summary["settings"], summary["gan_test"]
    finals = ", ".join(f"{name} {s['final_mean']:.3f}±{s['final_std']:.3f}" for name, s in per_setting.items()
                       if s["final_mean"] is not None)
    gan_text = f", GAN-test {gan_test['final_mean']:.3f}" if gan_test and gan_test["final_mean"] is not None else ""
    for line in chance_warnings(modality, summary):
        print(line)
    for item in summary["comparisons"]:
        print(f"classify {modality}: {item['setting']} vs {item['against']}: {item['difference']:+.3f}, "
              f"{item['verdict']} (n = {summary['counts']['real_test']} test images)")
    policy = summary["policy"]
    test = policy["test"]
    if test["accuracy"] is not None and test["real_accuracy"] is not None:
        print(f"classify {modality}: policy '{policy['chosen']}' ({policy['reason']}): test accuracy "
              f"{test['accuracy']:.3f} {_bracket(test['interval'])} against real only {test['real_accuracy']:.3f} "
              f"{_bracket(test['real_interval'])} (n = {test['images']} test images)")
    print(f"classify {modality}: final test accuracy over {seeds} seed(s) ({summary['seeds']['why']}): {finals}{gan_text} "
          f"({len(summary['classes'])} classes, {summary['wall_seconds']:.0f} s in training runs; {_speed_text(summary)}) -> {out_dir}")


def _bracket(interval: list[float] | None) -> str:
    return f"[{interval[0]:.3f}, {interval[1]:.3f}]" if interval else "[no interval]"


def _speed_text(summary: dict) -> str:
    speed = summary["throughput"]
    return (f"{speed['train_images_per_second'] or 0:.0f} training images/s, "
            f"{speed['eval_images_per_second'] or 0:.0f} evaluation images/s")
