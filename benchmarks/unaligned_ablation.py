"""Objectives for class-paired data, measured against issue 24's goals, per variant, direction and seed.

On a finished run folder's ``data/pairs`` (any dataset: the pairs say which images exist and their
splits), this trains one direction per variant and seed, translates every test input, and prints the
goal's numbers in the classifier view (features of a real-only classifier of the target modality, trained
here on the real training images of the run with the classify stage's settings):

* diversity: the score stage's within-class diversity ratio of generated over real test images of the class
  (64 px grey pixels and classifier features), median over classes, 95% bootstrap interval over classes
  (goal 1: >= 0.5);
* recall and coverage (k = 5) of generated vs the real training targets, beside the real test images' own
  (goal 1: >= half of real's);
* FID and KID (classifier view) of generated, flat mean colour, mean image and real test images against the
  real training targets (goal 2: generated below both no-learning baselines, outside the KID interval), and the
  class-wise KID: the mean over classes of each class's KID against that class's training targets
  (:func:`vtgen.stages.score.mean_over_classes`), which a set drawing one class's look for another cannot pass;
* GAN-test: the target classifier's accuracy on the generated images (Wilson 95% interval), beside its
  accuracy on real test targets and the input-modality classifier's on the real test inputs (goal 3:
  >= 0.8 x the lower of the two), and the same after a 1-pixel Gaussian blur of the images it is given
  (:func:`blurred`: a GAN-test that drops under blur while real images' does not was bought with pixel-scale
  patterns that fool the classifier, the risk of a loss through a classifier such as ``class_gan.semantic``);
* memorisation rate of generated vs real test images (goal 4: within the interval of real's);
* edge outliers: the share of images with a border band or corner wash, i.e. whose largest gap between an edge
  strip's mean colour and the interior's (:func:`edge_gap`) is above the 99th percentile of the real training
  targets' (about 0.01 for real images; a picture's defect that the distribution metrics average away);
* spectrum distance: the score stage's power-spectrum distance (:func:`vtgen.core.distribution.spectrum_distance`,
  decades of power) of the set against the real training targets; smooth outputs that lack a sensor's grain show here;
* fixed spikes: interior pixel positions (2 px in from the border) where the mean over the set of |grey − its 3 x 3
  median| is above 3 x the real training targets' largest (the score stage's fixed-dot check,
  :func:`vtgen.stages.score.dot_threshold` and :func:`vtgen.core.fixed_pattern.dot_map`): dots drawn at the same place
  in every output (a lattice of one-pixel spikes), which no real image has and the distribution metrics barely see.
* fixed share: the share of the set's fine-detail energy (each pixel minus its 3 x 3 mean) that the set's mean keeps
  (:func:`fixed_share`): about 1/n for detail at independent places, 1 for a pattern every image has with one sign.
* concentration: :func:`vtgen.core.translator.detail_concentration` over the set (what ``class_gan.fixed_pattern``
  reads per batch): how unevenly over pixel positions the set keeps its fine detail, whatever its sign. Compare
  both with the real held-out row, whose n is close.
* detail overlap: :func:`vtgen.core.translator.detail_overlap` (what ``class_gan.shared_detail`` reads per batch), the mean
  over :data:`OVERLAP_DRAWS` random batches of :data:`OVERLAP_BATCH` images of the set (:func:`mean_detail_overlap`): how
  alike two images' fine detail is, any sign, anywhere (about f² for a pattern that is a share f of every image's detail).

    python benchmarks/unaligned_ablation.py --run /tmp/xu --direction v2t --seeds 0 1 \\
        --variant pix2pix:objective=pix2pix --variant class_gan:objective=class_gan

A variant is ``name:key=value;key=value``; keys are ``translation`` keys (objective, conditioning as one kind
for this direction), ``class_gan.<key>`` or preset keys, set over the run folder's params.yaml with its recipe
(``translation.recipe``; ``auto`` as the run's pairs summary chose) applied, except the recipe's step count:
``--iterations`` sets it. SYNTHETIC results must be labelled as such.
``--truncation 1 0.5 0`` measures each trained generator once per psi its latent codes are scaled by
(``translate``'s truncation); ``--model <run>/models/v2t/all`` measures a main job's trained generator instead
of training one; ``--outputs sheets/*.pt`` measures test outputs an earlier ``--sheets`` run saved.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import yaml

from vtgen.core.classifier import predict, train_classifier, wilson_interval
from vtgen.core.distribution import (classifier_encoder, diversity_ratio, fid, flat_colour_set, grey_pixels,
                                     image_features, kid, mean_image_set, median_interval, memorisation, prdc_scores,
                                     spectrum_distance)
from vtgen.core.domain import DIRECTIONS
from vtgen.core.fixed_pattern import dot_map
from vtgen.core.gan import to_model_range
from vtgen.core.referee import at_side as resized  # area-resized uint8 tiles at the classifier's side
from vtgen.core.translator import detail_concentration, detail_overlap, fine_detail
from vtgen.io.checkpoints import load_translator
from vtgen.io.images import labelled_sheet, read_tiles, write_png
from vtgen.io.params import model_settings, validate_params, with_recipe
from vtgen.io.tables import PAIR_COLUMNS, read_table, SPLIT_COLUMNS
from vtgen.stages.generate import translate
from vtgen.stages.score import KID_SUBSETS, brightness_direction, dot_threshold, kid_subset_size, mean_over_classes
from vtgen.stages.train import (build_conditioning, build_guide, build_referee, load_pair_data, objective_settings,
                                output_settings, pairs_in, resolve_conditioning, resolve_objective, train_translator, with_frame_views)
from translation_quality import parse_variant, target_of  # the same name:key=value;... variants (benchmarks/ is on sys.path)

def real_classifier(splits, modality: str, params: dict, root: Path, classes: list[str], seed: int = 0):
    """The classify stage's real-only classifier of ``modality`` (trained with ``seed``) and its test accuracy with n."""
    cfg = params["classify"]
    settings = {k: cfg[k] for k in ("size", "width", "epochs", "batch_size", "lr")}
    index = {c: i for i, c in enumerate(classes)}

    def load(split):
        rows = splits[(splits["split"] == split) & (splits["modality"] == modality)].sort_values("path")
        return (read_tiles(list(rows["path"]), cfg["size"], root),
                torch.tensor([index[c] for c in rows["class"]]))

    (train_x, train_y), (test_x, test_y) = load("train"), load("test")
    run = train_classifier(train_x, train_y, test_x, test_y, len(classes), settings, seed=seed)
    return run.model, run.test_accuracy[-1], len(test_y)


def class_diversity(generated: torch.Tensor, real: torch.Tensor, classes_gen: np.ndarray, classes_real: np.ndarray,
                    view) -> tuple[float, float, float]:
    """Median over classes of the score stage's within-class diversity ratio (:func:`diversity_ratio`) in
    ``view`` (images -> rows), with its 95% bootstrap interval over classes (:func:`median_interval`)."""
    ratios = [diversity_ratio(view(generated[classes_gen == c]), view(real[classes_real == c]), resamples=0).ratio
              for c in sorted(set(classes_gen) & set(classes_real))
              if (classes_gen == c).sum() >= 2 and (classes_real == c).sum() >= 2]
    return median_interval(ratios)


def read_rate(conditioning, inputs: torch.Tensor, input_classes) -> float:
    """Share of uint8 ``inputs`` whose class an ``inferred`` conditioning's reader reads as ``input_classes``
    (their class names): how often the generator is told the class of what it translates."""
    told = conditioning.probabilities(to_model_range(inputs)).argmax(dim=1)
    return float((told == conditioning.labels(list(input_classes))).float().mean())


def run_variant(params, pairs, splits, direction, overrides, seed, iterations, threads, root, context,
                truncations=(1.0,), checkpoint_dir: Path | None = None) -> list[dict]:
    """Train one variant at one seed; one result per truncation psi of the test translations' latent codes.
    With ``checkpoint_dir`` the last step's checkpoint (generator, discriminator, optimisers) is kept there."""
    settings = dict(model_settings(params), iterations=iterations)
    run = dict(params["translation"], seed=seed, threads=threads, resume=False,
               checkpoint_every=iterations if checkpoint_dir else 10**9)
    run["class_gan"] = dict(run["class_gan"], iterations=None)  # --iterations rules, also over a recipe's
    for key, value in overrides.items():
        if key.startswith("class_gan."):
            inner = key.split(".", 1)[1]
            target_of(inner, run["class_gan"], {}, ("translation", "class_gan"))[inner] = value
        elif key == "conditioning":
            run["conditioning"] = dict(run["conditioning"], **{direction: value})
        else:
            target_of(key, run, settings)[key] = value
    size = settings["size"]
    train = load_pair_data(pairs, splits, direction, "all", size, root)
    validation = (load_pair_data(pairs, splits, direction, "all", size, root, split="val")
                  if not pairs_in(pairs, "val", "all").empty else None)
    objective, _ = resolve_objective(run["objective"], train)
    settings = objective_settings(settings, run, objective, direction)
    settings, _ = output_settings(settings, run, train.targets)
    train = with_frame_views(train, pairs, splits, direction, "all", settings.get("views", 1),
                             Path("data/roi/tiles.parquet"), params["roi"], size, seed, root)
    kind = resolve_conditioning(run["conditioning"][direction], objective, len(set(train.classes)))
    conditioning = build_conditioning(kind, pairs, "all", train, params["classify"], seed, run.get("inferred_epochs"),
                                      run.get("inferred_reader", "network"))
    started = time.perf_counter()
    guide = build_guide(settings, train, params["classify"], seed)
    referee = build_referee(settings, train, validation, params["classify"], seed)  # class_gan.select_every's judge
    result = train_translator(train, settings, run, direction, "all", checkpoint_dir, progress=False,
                              conditioning=conditioning,
                              guide=guide, validation=validation if referee is not None else None, referee=referee)
    seconds = time.perf_counter() - started
    if referee is not None:  # which snapshot select_every kept, and the referee's FID at each scoring
        scores = {row["step"]: round(row["val_fid"], 1) for row in result.history if "val_fid" in row}
        print(f"# select_every: kept step {(result.selected or {}).get('step', result.steps)} of {result.steps}; "
              f"referee FID by step {scores}", flush=True)
    inputs, input_classes = context["test_inputs"], context["test_input_classes"]
    labels = conditioning.labels(list(input_classes)) if conditioning.needs_labels else None
    if conditioning.kind == "inferred":  # how often the generator is told the test input's own class
        read = read_rate(conditioning, inputs, input_classes)
        low, high = wilson_interval(read, len(inputs))
        print(f"# conditioning inferred: the reader reads the test inputs' class at {read:.3f} "
              f"[{low:.3f}, {high:.3f}] (n = {len(inputs)})", flush=True)
    results = []
    for psi in truncations:
        generated = translate(result.generator.eval(), inputs, conditioning=conditioning, labels=labels,
                              truncation=psi)
        results.append({"objective": objective, "seconds": seconds, "generated": generated, "truncation": psi,
                        **goal_numbers(generated, input_classes, context)})
    return results


def write_sheet(path: Path, generated: torch.Tensor, context: dict, per_class: int = 4) -> None:
    """One row per class: ``per_class`` test inputs, their translations, and as many real test targets of the
    class (the pictures to look at beside the numbers), as the report's grids are drawn."""
    def images(batch: torch.Tensor) -> list[np.ndarray]:
        return list(batch[:per_class].permute(0, 2, 3, 1).numpy())

    rows = []
    for c in context["classes"]:
        inputs = torch.from_numpy(context["test_input_classes"] == c)
        targets = torch.from_numpy(context["test_target_classes"] == c)
        rows.append((c, [images(context["test_inputs"][inputs]), images(generated[inputs]),
                         images(context["test_targets"][targets])]))
    write_png(path, labelled_sheet(rows, ["input", "generated", "real of the class"], per_class))


def blurred(images: torch.Tensor, sigma: float = 1.0) -> torch.Tensor:
    """uint8 images through a Gaussian blur of ``sigma`` pixels (reflected borders): pixel-scale patterns that
    fool a classifier without looking like anything (adversarial stripes) do not survive it, the content of a
    real image mostly does, so GAN-test after it separates the two."""
    radius = max(1, round(3 * sigma))
    taps = torch.exp(-torch.arange(-radius, radius + 1, dtype=torch.float32) ** 2 / (2 * sigma ** 2))
    taps = taps / taps.sum()
    x = F.pad(images.float(), (radius,) * 4, mode="reflect")
    c = x.shape[1]
    x = F.conv2d(x, taps.view(1, 1, 1, -1).repeat(c, 1, 1, 1), groups=c)
    x = F.conv2d(x, taps.view(1, 1, -1, 1).repeat(c, 1, 1, 1), groups=c)
    return x.round().clamp(0, 255).to(torch.uint8)


def edge_gap(images: torch.Tensor, strip: int = 4) -> np.ndarray:
    """Per uint8 image (N x 3 x S x S), the largest over its four edge strips (``strip`` px wide) of the distance
    (RGB, 0-255) between the strip's mean colour and the mean colour of the interior inside all four strips."""
    x = images.float()
    interior = x[:, :, strip:-strip, strip:-strip].mean(dim=(2, 3))
    strips = [x[:, :, :, :strip], x[:, :, :, -strip:], x[:, :, :strip, :], x[:, :, -strip:, :]]
    gaps = torch.stack([(s.mean(dim=(2, 3)) - interior).norm(dim=1) for s in strips], dim=1)
    return gaps.max(dim=1).values.numpy()


def fixed_share(images: torch.Tensor) -> float:
    """Σₚ m(p)² / Σₚ mean_n h_n(p)², h = :func:`vtgen.core.translator.fine_detail` of ``images`` (N x C x H x W) and m its
    mean over the N images: the share of the fine-detail energy at the same place with the same sign in every image."""
    detail = fine_detail(images.float())
    return float(detail.mean(dim=0).pow(2).sum() / detail.pow(2).mean(dim=0).sum().clamp_min(1e-12))


OVERLAP_BATCH, OVERLAP_DRAWS = 16, 20  # a ratio of sums over pairs, so about the same at any batch size (training: 4)


def mean_detail_overlap(images: torch.Tensor) -> float:
    """Mean of :func:`vtgen.core.translator.detail_overlap` over :data:`OVERLAP_DRAWS` batches of :data:`OVERLAP_BATCH`
    images of ``images`` drawn without replacement (torch generator seeded 0, so a set always gets the same number)."""
    g = torch.Generator().manual_seed(0)
    size = min(OVERLAP_BATCH, len(images))
    return float(np.mean([float(detail_overlap(images[torch.randperm(len(images), generator=g)[:size]].float()))
                          for _ in range(OVERLAP_DRAWS)]))


def goal_numbers(generated: torch.Tensor, classes: np.ndarray, context: dict) -> dict:
    encoder, side = context["encoder"], context["side"]
    features = image_features(encoder, resized(generated, side))
    real_train, real_test = context["train_features"], context["test_features"]
    index = {c: i for i, c in enumerate(context["classes"])}
    correct = predict(context["model"], resized(generated, side)).numpy() == np.array([index[c] for c in classes])
    view_features = lambda images: image_features(encoder, resized(images, side))  # noqa: E731
    out = {
        "n": len(generated),
        "diversity_pixels": class_diversity(generated, context["test_targets"], classes,
                                            context["test_target_classes"], grey_pixels),
        "diversity_features": class_diversity(generated, context["test_targets"], classes,
                                              context["test_target_classes"], view_features),
        "prdc": prdc_scores(real_train, features),
        "fid": fid(real_train, features),
        "kid": kid(real_train, features),
        "kid_classwise": classwise_kid(features, classes, real_train, context["train_target_classes"]),
        "gan_test": float(correct.mean()),
        "gan_test_blurred": float((predict(context["model"], resized(blurred(generated), side)).numpy()
                                   == np.array([index[c] for c in classes])).mean()),
        "memorisation": memorisation(features, real_train, real_test).rate,
        "edge_outliers": float((edge_gap(generated) > context["edge_threshold"]).mean()),
        "spectrum": spectrum_distance(context["train_targets"], generated),
        "fixed_spikes": int((dot_map(generated) > context["spike_threshold"]).sum()),
        "fixed_share": fixed_share(generated),
        "concentration": float(detail_concentration(generated.float())),
        "overlap": mean_detail_overlap(generated),
        "brightness_outside": brightness_outside(generated, classes, context),
    }
    return out


def brightness_outside(generated: torch.Tensor, classes: np.ndarray, context: dict) -> float:
    """Share of ``generated`` darker or lighter than every real training target of its class (the score stage's
    :func:`vtgen.stages.score.brightness_direction`, its ``(all)`` row)."""
    no_groups = lambda n: np.zeros(n, dtype=object)  # noqa: E731 (the check reads no groups)
    sets = {("generated", "all"): (generated, np.asarray(classes), no_groups(len(generated))),
            "real_train": (context["train_targets"], context["train_target_classes"], no_groups(len(context["train_targets"]))),
            "real_test": (context["test_targets"], context["test_target_classes"], no_groups(len(context["test_targets"])))}
    table = brightness_direction("-", sets)
    overall = table[(table["class"] == "(all)") & (table["candidate"] == "generated")]
    return float(overall["share"].iloc[0]) if len(overall) else float("nan")


def classwise_kid(features: torch.Tensor, classes: np.ndarray, real: torch.Tensor, real_classes: np.ndarray):
    """(mean, low, high) over classes of each class's KID (generated of the class against real of the class;
    subsets of half the smaller set), :func:`vtgen.stages.score.mean_over_classes` of their stds."""
    values, stds = [], []
    for name in sorted(set(classes)):
        a, b = real[torch.from_numpy(real_classes == name)], features[torch.from_numpy(classes == name)]
        if min(len(a), len(b)) < 2:
            continue
        mean, std = kid(a, b, subsets=KID_SUBSETS, subset_size=kid_subset_size(a, b))
        values.append(mean)
        stds.append(std)
    return mean_over_classes(values, stds)


def prepare_context(params, pairs, splits, direction, root) -> dict:
    source, target = DIRECTIONS[direction]
    classes = sorted(set(pairs["class"]))
    model, real_acc, real_n = real_classifier(splits, target, params, root, classes)
    _, input_acc, input_n = real_classifier(splits, source, params, root, classes)
    side = params["classify"]["size"]
    size = model_settings(params)["size"]

    def tiles(split, modality):
        rows = splits[(splits["split"] == split) & (splits["modality"] == modality)].sort_values("path")
        return read_tiles(list(rows["path"]), size, root), rows["class"].to_numpy()

    train_targets, train_target_classes = tiles("train", target)
    test_targets, test_target_classes = tiles("test", target)
    test_inputs, test_input_classes = tiles("test", source)
    encoder = classifier_encoder(model)
    context = {"model": model, "encoder": encoder, "side": side, "classes": classes,
               "real_accuracy": (real_acc, real_n), "input_accuracy": (input_acc, input_n),
               "train_targets": train_targets, "train_target_classes": train_target_classes, "test_targets": test_targets,
               "test_target_classes": test_target_classes, "test_inputs": test_inputs,
               "test_input_classes": test_input_classes,
               "edge_threshold": float(np.quantile(edge_gap(train_targets), 0.99)),
               "spike_threshold": dot_threshold(train_targets),
               "train_features": image_features(encoder, resized(train_targets, side)),
               "test_features": image_features(encoder, resized(test_targets, side))}
    references = {"real held-out": (test_targets, test_target_classes),
                  "flat mean colour": (flat_colour_set(train_targets, len(test_inputs)), test_input_classes),
                  "mean image": (mean_image_set(train_targets, len(test_inputs)), test_input_classes)}
    context["references"] = {name: goal_numbers(images, cls, context) for name, (images, cls) in references.items()}
    return context


def row(name: str, seed, r: dict) -> str:
    def ci(t):
        return f"{t[0]:.2f} [{t[1]:.2f}, {t[2]:.2f}]"
    low, high = wilson_interval(r["gan_test"], r["n"])
    k, c = r["kid"], r["kid_classwise"]
    return (f"| {name} | {seed} | {r['n']} | {ci(r['diversity_pixels'])} | {ci(r['diversity_features'])} | "
            f"{r['prdc']['recall']:.2f} / {r['prdc']['coverage']:.2f} | {r['fid']:.1f} | "
            f"{k[0]:.4f} ± {1.96 * k[1]:.4f} | {c[0]:.4f} [{c[1]:.4f}, {c[2]:.4f}] | {r['gan_test']:.3f} [{low:.3f}, {high:.3f}] | {r['gan_test_blurred']:.3f} | "
            f"{r['memorisation']:.3f} | {r['edge_outliers']:.3f} | {r['spectrum']:.3f} | {r['fixed_spikes']} | {r['fixed_share']:.3f} | {r['concentration']:.2f} | {r['overlap']:.4f} | {r['brightness_outside']:.3f} | {r.get('seconds', 0):.0f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", default=".", help="a run folder holding params.yaml and data/pairs")
    parser.add_argument("--direction", choices=list(DIRECTIONS), default="v2t")
    parser.add_argument("--variant", action="append", default=[], help="name:key=value;key=value")
    parser.add_argument("--model", type=Path, help="measure this trained model folder (e.g. <run>/models/v2t/all) "
                                                   "instead of training variants")
    parser.add_argument("--outputs", type=Path, nargs="+", default=[],
                        help="measure these saved test outputs (the .pt files --sheets writes) of this run folder")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--truncation", type=float, nargs="+", default=[1.0],
                        help="psi values the test translations' latent codes are scaled by (one row each; 1 = plain draw)")
    parser.add_argument("--sheets", type=Path, help="folder for one PNG per run, variant and seed: per class, test inputs, "
                                                   "their translations and real test targets (and the outputs as .pt)")
    parser.add_argument("--checkpoints", type=Path, help="folder for each trained variant's last checkpoint "
                                                        "(<direction>_<variant>_<seed>/last.pt, discriminator included)")
    args = parser.parse_args()
    if not args.variant and not args.model and not args.outputs:
        parser.error("give --variant (train and measure), --model (measure a trained model) or --outputs")
    root = Path(args.run).resolve()
    kind = json.loads((root / "data" / "pairs" / "summary.json").read_text()).get("data_kind")  # what recipe auto reads
    params = with_recipe(validate_params(yaml.safe_load((root / "params.yaml").read_text())), kind)
    torch.set_num_threads(args.threads)
    pairs = read_table(root / "data" / "pairs" / f"{args.direction}.parquet", PAIR_COLUMNS, "pairs")
    splits = read_table(root / "data" / "pairs" / "splits.parquet", SPLIT_COLUMNS, "splits")
    context = prepare_context(params, pairs, splits, args.direction, root)
    (acc, n), (in_acc, in_n) = context["real_accuracy"], context["input_accuracy"]
    recipe = params["translation"]["recipe"]
    applied = "" if recipe == "none" else f" (the run folder's recipe {recipe!r} applied, its iterations replaced)"
    print(f"# {root} {args.direction}, {args.iterations} iterations{applied}; real-only accuracy: target {acc:.3f} (n = {n}), "
          f"input {in_acc:.3f} (n = {in_n}); GAN-test goal >= {0.8 * min(acc, in_acc):.3f}", flush=True)
    header = ("| variant | seed | n | diversity pixels [95%] | diversity features [95%] | recall / coverage | FID | "
              "KID ± 95% | class-wise KID [95%] | GAN-test [95%] | GAN-test, blurred | memorisation | edge outliers | "
              "spectrum distance | fixed spikes | fixed share | concentration | detail overlap | brightness outside | train s |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [row(name, "-", r) for name, r in context["references"].items()]
    if args.model:
        generator, meta = load_translator(args.model)
        if meta["direction"] != args.direction:
            parser.error(f"{args.model} translates {meta['direction']}, not {args.direction}")
        inputs, input_classes = context["test_inputs"], context["test_input_classes"]
        conditioning = meta["conditioning"]
        labels = conditioning.labels(list(input_classes)) if conditioning.needs_labels else None
        for psi in args.truncation:
            generated = translate(generator, inputs, conditioning=conditioning, labels=labels, truncation=psi)
            result = {"seconds": 0.0, **goal_numbers(generated, input_classes, context)}
            lines.append(row(f"{args.model.parent.parent.parent.name} model, psi {psi:g}", "-", result))
            if args.sheets:
                args.sheets.mkdir(parents=True, exist_ok=True)
                sheet = args.sheets / f"{root.name}_{args.direction}_model_psi{psi:g}.png"
                write_sheet(sheet, generated, context)
                torch.save(generated, sheet.with_suffix(".pt"))  # the test outputs, for --outputs or the probe
            print(lines[-1], flush=True)
    for path in args.outputs:
        generated = torch.load(path)
        if len(generated) != len(context["test_inputs"]):
            parser.error(f"{path}: {len(generated)} outputs, but {root} has {len(context['test_inputs'])} test inputs")
        lines.append(row(f"{path.stem} (saved)", "-", {"seconds": 0.0, **goal_numbers(
            generated, context["test_input_classes"], context)}))
        print(lines[-1], flush=True)
    for text in args.variant:
        name, overrides = parse_variant(text)
        for seed in args.seeds:
            for result in run_variant(params, pairs, splits, args.direction, overrides, seed, args.iterations,
                                      args.threads, root, context, args.truncation,
                                      args.checkpoints / f"{args.direction}_{name}_{seed}" if args.checkpoints else None):
                psi = result["truncation"]
                label = name if psi == 1.0 else f"{name}, psi {psi:g}"
                lines.append(row(f"{label} ({result['objective']})", seed, result))
                if args.sheets:
                    args.sheets.mkdir(parents=True, exist_ok=True)
                    suffix = "" if psi == 1.0 else f"_psi{psi:g}"  # the run's name: one folder, many runs
                    sheet = args.sheets / f"{root.name}_{args.direction}_{name}_{seed}{suffix}.png"
                    write_sheet(sheet, result["generated"], context)
                    torch.save(result["generated"], sheet.with_suffix(".pt"))  # the test outputs, to measure again
                print(lines[-1], flush=True)
    print("\n" + header + "\n" + "\n".join(lines))


if __name__ == "__main__":
    main()
