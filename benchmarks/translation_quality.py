"""Translation quality of training variants, per class and seed, on a finished main job's data.

For each variant (preset keys and ``conditioning`` overridden on top of params.yaml) and seed, trains one
direction on ``data/pairs`` (train split), translates the aligned test pairs, and prints:

* aligned Colour-SSIM of the generated images against their ground truth, overall and per class, next to
  the flat mean colour of the class's training targets (the score stage's ``flat_mean_colour``);
* GAN-test: the share of generated test images that the classify stage's real-only classifier of the
  target modality (``data/classify/<modality>/encoder.pt``) puts in their own class;
* spectrum: the score stage's spectrum distance (mean |difference| of log10 radial power profiles, decades)
  of the generated images, and of the nearest-neighbour baseline's, against the real targets of the pairs.

    python benchmarks/translation_quality.py --direction t2v --seeds 0 1 --iterations 1500 \\
        --variant none:conditioning=none --variant class:conditioning=class

A variant is ``name:key=value;key=value``; keys are preset keys (``ngf``, ``gan_loss``, ...) or
``conditioning``. Needs the main job's ``data/pairs`` and ``data/classify`` (run ``snakemake --cores 2``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from vtgen.core.classifier import predict, wilson_interval
from vtgen.core.distribution import spectrum_distance
from vtgen.core.domain import DIRECTIONS
from vtgen.core.metrics import colour_ssim
from vtgen.io.classifiers import load_classifier
from vtgen.io.params import SCHEMA_PATH, model_settings, validate_params
from vtgen.io.tables import PAIR_COLUMNS, read_table, SPLIT_COLUMNS
from vtgen.stages.generate import translate
from vtgen.stages.score import reference_candidates
from vtgen.stages.train import build_conditioning, load_pair_data, resolve_conditioning, train_translator


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, body = text.partition(":")
    overrides = {}
    for item in filter(None, body.split(";")):
        key, _, value = item.partition("=")
        overrides[key.strip()] = yaml.safe_load(value)
    return name, overrides


def schema_keys(*section: str) -> set[str]:
    """The keys params.schema.yaml allows in ``section`` (e.g. 'translation', 'class_gan'), optional ones included:
    a run folder's params.yaml written before an optional key existed lacks it."""
    node = yaml.safe_load(SCHEMA_PATH.read_text())
    for name in section:
        node = node["properties"][name]
    return set(node["properties"])


def target_of(key: str, run: dict, settings: dict, section: tuple[str, ...] = ("translation",)) -> dict:
    """The dict a variant's ``key`` sets: ``run`` (the params ``section``) or ``settings`` (the preset's); raise
    ValueError for a key that is in neither, which would otherwise change nothing and leave the variant the default."""
    run_keys = set(run) | schema_keys(*section)
    if key in run_keys or key in settings:
        return run if key in run_keys else settings
    raise ValueError(f"variant key {key!r} is neither a {'.'.join(section)} key nor a preset key, so it would change "
                     f"nothing; {'.'.join(section)} keys: {', '.join(sorted(run_keys))}; preset keys: {', '.join(sorted(settings))}")


def run_variant(params: dict, pairs, splits, direction: str, overrides: dict, seed: int, iterations: int,
                threads: int, encoder, encoder_record, root: Path = Path(".")) -> dict:
    settings = dict(model_settings(params), iterations=iterations)
    run = dict(params["translation"], seed=seed, threads=threads, checkpoint_every=10**9, resume=False)
    for key, value in overrides.items():
        target_of(key, run, settings)[key] = value
    size = settings["size"]
    train = load_pair_data(pairs, splits, direction, "all", size, root)
    test = load_pair_data(pairs, splits, direction, "all", size, root, split="test")
    kind = run["conditioning"][direction] if isinstance(run["conditioning"], dict) else run["conditioning"]
    conditioning = build_conditioning(resolve_conditioning(kind, "pix2pix", len(set(train.classes))), pairs, "all", train)  # trains pix2pix
    started = time.perf_counter()
    result = train_translator(train, settings, run, direction, "all", progress=False, conditioning=conditioning)
    seconds = time.perf_counter() - started
    keep = test.aligned.nonzero().flatten()
    inputs, truths = test.inputs[keep], test.targets[keep]
    classes = np.array([test.classes[i] for i in keep.tolist()])
    labels = conditioning.labels(list(classes)) if conditioning.kind != "none" else None
    generated = translate(result.generator.eval(), inputs, conditioning=conditioning, labels=labels)
    references = reference_candidates(inputs, classes, train.inputs, train.targets, np.array(train.classes))
    flat = references["flat_mean_colour"]
    hwc = lambda t: t.permute(0, 2, 3, 1).numpy()  # noqa: E731
    ssim, ssim_flat = colour_ssim(hwc(generated), hwc(truths), 255.0), colour_ssim(hwc(flat), hwc(truths), 255.0)
    side = encoder_record["size"]
    resized = generated if generated.shape[-1] == side else F.interpolate(
        generated.float(), size=(side, side), mode="area").round().clamp(0, 255).to(torch.uint8)
    index = {c: i for i, c in enumerate(encoder_record["classes"])}
    predicted = predict(encoder, resized).numpy()
    correct = predicted == np.array([index[c] for c in classes])
    per_class = {c: (float(ssim[classes == c].mean()), float(ssim_flat[classes == c].mean()),
                     float(correct[classes == c].mean())) for c in sorted(set(classes))}
    return {"ssim": float(ssim.mean()), "flat": float(ssim_flat.mean()), "gan_test": float(correct.mean()),
            "n": len(classes), "per_class": per_class, "seconds": seconds,
            "spectrum": spectrum_distance(truths, generated),
            "spectrum_nn": spectrum_distance(truths, references["nearest_neighbour"])}


def real_accuracy(params: dict, pairs, splits, direction: str, encoder, encoder_record, root: Path) -> tuple[float, int]:
    """The classifier's accuracy on the real targets of the same aligned test pairs: the level GAN-test is read against."""
    test = load_pair_data(pairs, splits, direction, "all", model_settings(params)["size"], root, split="test")
    keep = test.aligned.nonzero().flatten()
    truths, side = test.targets[keep], encoder_record["size"]
    truths = truths if truths.shape[-1] == side else F.interpolate(
        truths.float(), size=(side, side), mode="area").round().clamp(0, 255).to(torch.uint8)
    index = {c: i for i, c in enumerate(encoder_record["classes"])}
    truth = np.array([index[test.classes[i]] for i in keep.tolist()])
    return float((predict(encoder, truths).numpy() == truth).mean()), len(truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--direction", choices=list(DIRECTIONS), default="t2v")
    parser.add_argument("--variant", action="append", required=True, help="name:key=value;key=value")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--data", default="data", help="the main job's data folder")
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--per-class", action="store_true", help="print the per-class table too")
    args = parser.parse_args()
    params = validate_params(yaml.safe_load(Path(args.params).read_text()))
    data = Path(args.data)
    pairs = read_table(data / "pairs" / f"{args.direction}.parquet", PAIR_COLUMNS, "pairs")
    splits = read_table(data / "pairs" / "splits.parquet", SPLIT_COLUMNS, "splits")
    target = DIRECTIONS[args.direction][1]
    encoder, record = load_classifier(data / "classify" / target / "encoder.pt")
    rows = []
    for text in args.variant:
        name, overrides = parse_variant(text)
        for seed in args.seeds:
            result = run_variant(params, pairs, splits, args.direction, overrides, seed, args.iterations,
                                 args.threads, encoder, record, data.resolve().parent)
            rows.append((name, seed, result))
            print(f"# {name} seed {seed}: SSIM {result['ssim']:.3f} (flat {result['flat']:.3f}), GAN-test "
                  f"{result['gan_test']:.3f}, spectrum {result['spectrum']:.3f} (nearest neighbour "
                  f"{result['spectrum_nn']:.3f}), {result['seconds']:.0f} s", flush=True)
    real, n = real_accuracy(params, pairs, splits, args.direction, encoder, record, data.resolve().parent)
    low, high = wilson_interval(real, n)
    print(f"\n{args.direction}, {args.iterations} iterations, {args.threads} thread(s); n = aligned test pairs; "
          f"the classifier on the real targets of these pairs: {real:.3f} [{low:.3f}, {high:.3f}] (n = {n})\n")
    print("| variant | seed | n | aligned Colour-SSIM | flat mean colour | classes above flat | GAN-test (95% CI) "
          "| spectrum (nearest neighbour) | train s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, seed, r in rows:
        above = sum(s > f for s, f, _ in r["per_class"].values())
        low, high = wilson_interval(r["gan_test"], r["n"])
        print(f"| {name} | {seed} | {r['n']} | {r['ssim']:.3f} | {r['flat']:.3f} | {above}/{len(r['per_class'])} | "
              f"{r['gan_test']:.3f} [{low:.3f}, {high:.3f}] | {r['spectrum']:.3f} ({r['spectrum_nn']:.3f}) | "
              f"{r['seconds']:.0f} |")
    if args.per_class:
        print("\n| variant | seed | class | SSIM | flat | GAN-test |\n|---|---|---|---|---|---|")
        for name, seed, r in rows:
            for cls, (s, f, g) in r["per_class"].items():
                print(f"| {name} | {seed} | {cls} | {s:.3f} | {f:.3f} | {g:.2f} |")


if __name__ == "__main__":
    main()
