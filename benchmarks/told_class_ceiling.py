"""How recognisable can a generator that is *not* told the class be? Issue 24, goal 3, on one run folder.

A generator trained with ``conditioning: class`` (or ``inferred``) is asked to translate every test input while
told, in turn: the true class; for an ``inferred`` model, the class its own stored reader reads; the class the
classify stage's network (real-only, trained here on the run's training inputs as the score stage's classifiers
are) reads from the input; the class a hand-crafted-feature reader reads from it (``translation.inferred_reader:
features``, :mod:`vtgen.core.readers`, fitted on the training inputs); and a random class. Each row gives the
reader's accuracy on the test inputs and the GAN-test of the translations (the target modality's real-only
classifier, :func:`unaligned_ablation.prepare_context`), with Wilson 95% intervals, beside goal 3's threshold
(0.8 x the lower real-only accuracy). ``--truncation`` scales the latent codes as ``generate.truncation`` does.

The true-class row is the ceiling of any reader: a generator not told the class is at most that recognisable.
GAN-test is roughly a*r + (1 - a)(1 - r)/(K - 1) for a reader of accuracy a and a told-class GAN-test r
(Thirteenth round of benchmarks/README.md).

Beside each reading, the *realistic oracle*: the GAN-test that outputs indistinguishable from real ones would get,
each a real held-out target image of the class read. It is an expectation, computed exactly from the judge's
confusion on the real test targets: mean over test inputs i of C[k_i, c_i], C[k, c] the share of real test
targets of class k the judge calls c, k_i the class read and c_i the true one. No generator is needed for it, so
it is printed for any run; the generator columns need one conditioned on the class.

``--judges N`` scores with N real-only classifiers of the target modality (seeds 0..N-1, as the classify stage
trains three) and averages: GAN-test, the oracle, the real-only accuracies and so goal 3's threshold.
``--scale-floors`` fits the feature reader once per floor (:data:`vtgen.core.readers.SCALE_FLOOR` by default; 0 is
plain standardisation), one row each: how the floor moves the reading of the test inputs (Sixty-second round).

    python benchmarks/told_class_ceiling.py --run <run folder> --direction v2t --judges 3
    python benchmarks/told_class_ceiling.py --run <run folder> --direction v2t --scale-floors 0 0.1 0.3
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
import yaml

from vtgen.core.classifier import predict, wilson_interval
from vtgen.core.conditioning import Conditioning
from vtgen.core.domain import DIRECTIONS
from vtgen.core.gan import to_model_range
from vtgen.core.readers import SCALE_FLOOR, fit_feature_reader
from vtgen.core.translation import translate
from vtgen.io.checkpoints import load_translator
from vtgen.io.images import read_tiles
from vtgen.io.params import validate_params
from vtgen.io.tables import PAIR_COLUMNS, read_table, SPLIT_COLUMNS
from unaligned_ablation import prepare_context, real_classifier, resized  # benchmarks/ is on sys.path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=Path("."), help="a finished run folder")
    parser.add_argument("--direction", choices=list(DIRECTIONS), default="v2t")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--truncation", type=float, default=1.0, help="psi of the latent codes (generate.truncation)")
    parser.add_argument("--judges", type=int, default=1, help="real-only classifiers (seeds 0..N-1) averaged over")
    parser.add_argument("--scale-floors", type=float, nargs="+", default=[SCALE_FLOOR],
                        help="the hand-crafted-feature reader's scale floor(s), one row each (0: plain standardisation)")
    args = parser.parse_args()
    root = args.run.resolve()
    torch.set_num_threads(args.threads)
    params = validate_params(yaml.safe_load((root / "params.yaml").read_text()))
    pairs = read_table(root / "data" / "pairs" / f"{args.direction}.parquet", PAIR_COLUMNS, "pairs")
    splits = read_table(root / "data" / "pairs" / "splits.parquet", SPLIT_COLUMNS, "splits")
    generator, meta = load_translator(root / "models" / args.direction / "all")
    own, kind = meta["conditioning"], meta["conditioning"].kind
    told = kind in ("class", "inferred")  # else only the realistic oracle is printed
    conditioning = Conditioning("class", own.classes) if told else None  # the same one-hot maps, told any class
    context = prepare_context(params, pairs, splits, args.direction, root)
    classes, source = context["classes"], DIRECTIONS[args.direction][0]
    index = {c: i for i, c in enumerate(classes)}
    truth = np.array([index[c] for c in context["test_input_classes"]])
    (acc, n), (in_acc, in_n) = context["real_accuracy"], context["input_accuracy"]
    judges, target = [context["model"]], DIRECTIONS[args.direction][1]
    for seed in range(1, args.judges):  # seed 0 is the context's
        model, target_acc, _ = real_classifier(splits, target, params, root, classes, seed=seed)
        judges.append(model)
        acc += target_acc
        in_acc += real_classifier(splits, source, params, root, classes, seed=seed)[1]
    acc, in_acc = acc / len(judges), in_acc / len(judges)
    threshold = 0.8 * min(acc, in_acc)

    rows = splits[(splits["split"] == "train") & (splits["modality"] == source)].sort_values("path")
    train_inputs = read_tiles(list(rows["path"]), context["test_inputs"].shape[-1], root)
    train_labels = torch.tensor([index[c] for c in rows["class"]])
    by_features = []
    for floor in args.scale_floors:
        reader = fit_feature_reader(train_inputs, train_labels, len(classes), scale_floor=floor)
        with torch.no_grad():
            by_features.append((f"hand-crafted features (scale floor {floor:g})",
                                reader(context["test_inputs"]).argmax(dim=1).numpy()))
    network, _, _ = real_classifier(splits, source, params, root, classes)
    by_network = predict(network, resized(context["test_inputs"], params["classify"]["size"])).numpy()
    randomly = np.random.default_rng(0).integers(0, len(classes), len(truth))
    readings = [("the truth", truth), ("classify's network", by_network), *by_features]
    if kind == "inferred":  # the reader stored in the model file, as the generate stage reads
        reader_name = (own.classifier_settings or {}).get("reader", "network")
        by_own = own.probabilities(to_model_range(context["test_inputs"])).argmax(dim=1).numpy()
        readings.append((f"the model's own reader ({reader_name})", by_own))
    readings.append(("a random draw", randomly))

    confusions = [judge_confusion(judge, context) for judge in judges]
    print(f"# {root} {args.direction} ({kind}); real-only accuracy (mean of {len(judges)} judges): target {acc:.3f} "
          f"(n = {n}), input {in_acc:.3f} (n = {in_n}); goal 3: GAN-test >= {threshold:.3f}\n")
    print("| told the class read by | reader accuracy [95%] | GAN-test [95%] | realistic oracle's GAN-test [95%] | n |\n"
          "|---|---|---|---|---|")
    for name, labels in readings:
        if told:
            generated = translate(generator, context["test_inputs"], conditioning=conditioning,
                                  labels=torch.as_tensor(labels, dtype=torch.int64), truncation=args.truncation)
            called = [predict(judge, resized(generated, context["side"])).numpy() for judge in judges]
            score = float(np.mean([(c == truth).mean() for c in called]))
            gl, gh = wilson_interval(score, len(truth))
            told_cell = f"{score:.3f} [{gl:.3f}, {gh:.3f}]"
        else:
            told_cell = f"- (model conditioned on '{kind}')"
        read = float((labels == truth).mean())
        oracle = float(np.mean([confusion[labels, truth].mean() for confusion in confusions]))
        (rl, rh), (ol, oh) = wilson_interval(read, len(truth)), wilson_interval(oracle, len(truth))
        print(f"| {name} | {read:.3f} [{rl:.3f}, {rh:.3f}] | {told_cell} | {oracle:.3f} [{ol:.3f}, {oh:.3f}] "
              f"| {len(truth)} |", flush=True)


def judge_confusion(judge, context: dict) -> np.ndarray:
    """C[k, c]: the share of the real test targets of class k that ``judge`` (a real-only classifier of the target
    modality) calls c; a class without test targets gets a row of zeros."""
    classes = context["classes"]
    index = {c: i for i, c in enumerate(classes)}
    truth = np.array([index[c] for c in context["test_target_classes"]])
    called = predict(judge, resized(context["test_targets"], context["side"])).numpy()
    confusion = np.zeros((len(classes), len(classes)))
    np.add.at(confusion, (truth, called), 1.0)
    return confusion / np.maximum(confusion.sum(axis=1, keepdims=True), 1.0)


if __name__ == "__main__":
    main()
