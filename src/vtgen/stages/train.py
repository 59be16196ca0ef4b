"""Train stage: one conditional GAN per direction (V2T, T2V) and scope entry.

``train_translator`` is the loop around :class:`vtgen.core.translator.TranslatorTraining`: it draws
batches from the pair table (aligned pairs as they are; unaligned ones get a fresh input from the
same class at every draw, as the authors did), applies the paper's random positioning, runs one
step per batch, logs window-averaged losses, stops a diverging run, writes checkpoints atomically
and resumes from them. ``run_train`` is the stage around it: it reads the pair tables, writes the
final generator, ``train.json`` and the dvclive loss log into one output folder atomically.

A checkpoint is resumed only when its parameters, its training data and the code of this stage
(every vtgen file it imports) all match, and only into a run that still has steps to do.

Divergence that never reaches NaN is caught by generous bounds, checked at every logged window:
the generator's weight norm may grow to ``WEIGHT_GROWTH_LIMIT`` times its value at step 0; a
logged loss may reach ``LOSS_GROWTH_LIMIT`` times the median of the earlier windows of that loss
(and at least ``LOSS_FLOOR``); at the end of a run of at least ``MIN_VAL_CHECK_STEPS``, the
validation L1 may be at most the larger of ``VAL_WORSE_FACTOR`` times and ``VAL_WORSE_MARGIN``
above the untrained generator's. Measured on the ``fast`` preset (structured pairs, 40 steps at
lr 2e-4): weight norm 1.0x, validation L1 0.48 -> 0.35; at lr 1e3 the weight norm is 3e4x after
two steps.
"""

from __future__ import annotations

import hashlib
import json
import os
import statistics
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from tqdm import tqdm

from vtgen.core.classifier import train_classifier
from vtgen.core.conditioning import Conditioning, INPUT_READERS, typical_images
from vtgen.core.device import resolve_device, resolve_precision
from vtgen.core.domain import DIRECTIONS
from vtgen.core.gan import random_positioning, to_model_range, to_uint8
from vtgen.core.metrics import colour_ssim
from vtgen.core.models import count_parameters, fixed_codes, grey_targets
from vtgen.core.readers import fit_feature_reader
from vtgen.core.referee import at_side, distinct_images, Referee, train_referee
from vtgen.core.roi import random_crops
from vtgen.core.translator import LOSS_NAMES, STATE_KEYS, training_step_flops, TranslatorTraining
from vtgen.io.checkpoints import input_preparation, save_atomic, save_generator
from vtgen.io.timing import split_times, write_timing
from vtgen.io.images import atomic_output_dir, read_for_roi, read_tiles, resize_tiles
from vtgen.io.limits import check_training_fits
from vtgen.io.params import model_settings
from vtgen.io.provenance import code_fingerprint
from vtgen.io.tables import PAIR_COLUMNS, read_table, SPLIT_COLUMNS

CHECKPOINT_NAME = "last.pt"
STALE_SUFFIX = ".stale"  # an unreadable or incompatible checkpoint is renamed last.pt -> last.pt.stale
WEIGHT_GROWTH_LIMIT = 1e3  # ‖θ_G‖₂ at most 1e3 x its step-0 value (the default preset stays within 1e2)
LOSS_GROWTH_LIMIT = 1e3  # a loss window mean at most 1e3 x the median of the earlier windows ...
LOSS_FLOOR = 100.0  # ... or this, whichever is larger (BCE of 100 means logits of about 100)
VAL_WORSE_FACTOR = 1.5  # final validation L1 at most 1.5 x the untrained generator's ...
VAL_WORSE_MARGIN = 0.25  # ... or that plus 0.25 on [-1, 1], whichever is larger; checked only after
GUIDE_SEED_OFFSET = 7919  # class_gan.semantic's classifier seed = translation.seed + this (not a classify.seeds entry)
REFEREE_SEED_OFFSET = 104729  # class_gan.select_every's referee classifier seed = translation.seed + this
SELECTION_INPUTS_PER_CLASS = 6  # training inputs of each class select_every translates when there is no validation split
MIN_VAL_CHECK_STEPS = 22  # steps, when BatchNorm's running statistics (momentum 0.1) are >= 90% from training
# what a run took, not what it made: timing.json keeps them, train.json the rest (so a rerun that trains nothing new,
# or trains the same weights again, writes the same train.json)
RUN_TIMES = {"wall_seconds", "seconds_per_iteration", "resumed_from_step", "seconds", "fixed_large_seconds_estimate"}
CHECKPOINT_FIELDS = ("fingerprint", "step", "history", "seconds", "baseline", *STATE_KEYS, "sampler_rng", "torch_rng")
CHANGED = {"params": "the training parameters (preset, seed, precision)", "data": "the training pairs",
           "code": "the code that defines training"}


class TrainingDiverged(RuntimeError):
    """Training left its range (non-finite or exploding losses or weights, or a final validation L1 worse
    than the untrained generator's); nothing diverged was saved."""


@dataclass
class PairData:
    """Training pairs as uint8 tensors N x 3 x S x S, with what is needed to redraw unaligned inputs.

    ``input_pool[c]`` holds indices into ``pool_images`` of every training input tile of class
    ``c``; a class pair (``fixed`` False) draws its input from there at every step. ``fixed`` marks
    pixel and name pairs, which keep their own input; it defaults to ``aligned``.
    """

    inputs: torch.Tensor
    targets: torch.Tensor
    classes: list[str]
    aligned: torch.Tensor
    pool_images: torch.Tensor
    input_pool: dict[str, torch.Tensor] = field(default_factory=dict)
    fixed: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.fixed is None:
            self.fixed = self.aligned

    def pairs_by_class(self) -> dict[str, torch.Tensor]:
        """Indices of the pairs of each class (computed once)."""
        if not hasattr(self, "_by_class"):
            classes = np.array(self.classes)
            self._by_class = {c: torch.from_numpy(np.flatnonzero(classes == c)) for c in sorted(set(self.classes))}
        return self._by_class

    def fingerprint(self) -> str:
        """SHA-256 of the pixel data and pairing, so a checkpoint is only resumed on the same data."""
        digest = hashlib.sha256()
        for tensor in (self.inputs, self.targets, self.aligned, self.fixed, self.pool_images):
            digest.update(tensor.numpy().tobytes())
        digest.update(json.dumps(self.classes).encode())
        return digest.hexdigest()


def pairs_in(pairs: pd.DataFrame, split: str, scope: str) -> pd.DataFrame:
    """Rows of a pair table in ``split`` and ``scope`` ('all' or one class)."""
    chosen = pairs[pairs["split"] == split]
    return chosen if scope == "all" else chosen[chosen["class"] == scope]


def load_pair_data(pairs: pd.DataFrame, splits: pd.DataFrame, direction: str, scope: str, size: int,
                   root: Path = Path("."), split: str = "train") -> PairData:
    """Pairs of ``split`` for ``direction`` and ``scope`` ('all' or one class) from the pairing stage's tables."""
    if scope != "all" and scope not in set(pairs["class"]):
        raise ValueError(f"translation.scope: class '{scope}' has no {direction} pairs "
                         f"(classes: {', '.join(sorted(set(pairs['class'])))})")
    train = pairs_in(pairs, split, scope)
    if train.empty:
        raise ValueError(f"{direction}/{scope}: no {split} pairs")
    pool = input_pool_rows(train, splits, direction, split)
    pool_classes = pool["class"].to_numpy()
    return PairData(
        inputs=read_tiles(list(train["input_path"]), size, root),
        targets=read_tiles(list(train["target_path"]), size, root),
        classes=list(train["class"]),
        aligned=torch.tensor(train["aligned"].to_numpy(dtype=bool)),
        fixed=torch.tensor(train["pair_kind"].isin(["pixel", "name"]).to_numpy(dtype=bool)),
        pool_images=read_tiles(list(pool["path"]), size, root),
        input_pool={c: torch.from_numpy(np.flatnonzero(pool_classes == c)) for c in sorted(set(train["class"]))},
    )


def input_pool_rows(rows: pd.DataFrame, splits: pd.DataFrame, direction: str, split: str) -> pd.DataFrame:
    """The split table's tiles of ``split`` in ``direction``'s input modality and the classes of ``rows``,
    sorted by path: the inputs a class pair draws from."""
    source_mod = DIRECTIONS[direction][0]
    return splits[(splits["split"] == split) & (splits["modality"] == source_mod)
                  & splits["class"].isin(set(rows["class"]))].sort_values("path")


def frame_views(tile_paths: list[str], tiles: pd.DataFrame, tiles_dir: Path, roi: dict, count: int, size: int,
                seed: int, root: Path = Path(".")) -> torch.Tensor:
    """``count`` random crops of the frame behind each tile (:func:`vtgen.core.roi.random_crops`: the ROI
    rule's side and cleaning, at random places in the frame's region), as a uint8
    ``len(tile_paths) * count`` x 3 x ``size`` x ``size`` tensor, tile by tile. Each tile's crops come from a
    generator seeded by ``seed`` and the tile's path, whatever other tiles are asked for. ``tiles`` is the
    roi stage's table; its ``tile_path`` is relative to ``tiles_dir``, and a relative frame path to ``root``.
    ValueError naming the tile or frame when a tile is not in the table or its frame cannot be read or cut."""
    def where(path) -> str:  # one spelling for a path given relative to root or absolute
        return os.path.abspath(os.path.join(root, path))

    by_path = {where(Path(tiles_dir) / rel): (image, modality) for rel, image, modality
               in zip(tiles["tile_path"], tiles["image_path"], tiles["modality"])}
    crops = []
    for path in tile_paths:
        key = where(path)
        if key not in by_path:
            raise ValueError(f"{path}: tile not in the roi stage's table under {tiles_dir}; rerun the roi and pairs stages")
        image_path, modality = by_path[key]
        rng = np.random.default_rng([seed, zlib.crc32(Path(path).as_posix().encode())])
        try:
            _, views = random_crops(read_for_roi(Path(root) / image_path), modality, roi, count, rng)
        except (OSError, ValueError) as exc:
            raise ValueError(f"{image_path}: {exc} (the frame of {path}; has it changed since the roi stage?)") from exc
        if len(views) != count:
            raise ValueError(f"{image_path}: its region is too small for roi.crop_fraction {roi['crop_fraction']}")
        crops.extend(views)
    if not crops:
        return torch.zeros((0, 3, size, size), dtype=torch.uint8)
    return resize_tiles(torch.from_numpy(np.stack(crops)).permute(0, 3, 1, 2).contiguous(), size)


def with_frame_views(data: PairData, pairs: pd.DataFrame, splits: pd.DataFrame, direction: str, scope: str,
                     views: int, tiles_path: Path, roi: dict, size: int, seed: int, root: Path = Path(".")) -> PairData:
    """``data`` (the training pairs of :func:`load_pair_data`) with ``views - 1`` more crops of every frame
    (:func:`frame_views`) behind its class pairs' targets and behind its input pool: each crop of a target
    is one more class pair of that class, each crop of an input one more input of its class. Pixel and
    name pairs are kept as they are and get no crops (a crop elsewhere in the frame is not their partner).
    ``views`` 1 returns ``data`` itself."""
    if views <= 1:
        return data
    tiles = read_table(Path(root) / tiles_path, ["tile_path", "image_path", "modality"], "the roi stage's tile table")
    tiles_dir, extra = Path(tiles_path).parent / "tiles", views - 1
    train = pairs_in(pairs, "train", scope)
    pool = input_pool_rows(train, splits, direction, "train")
    free = np.flatnonzero(~data.fixed.numpy())
    rows = np.repeat(free, extra)
    targets = frame_views(list(train["target_path"].iloc[free]), tiles, tiles_dir, roi, extra, size, seed, root)
    inputs = frame_views(list(pool["path"]), tiles, tiles_dir, roi, extra, size, seed, root)
    view_classes = np.repeat(pool["class"].to_numpy(), extra)
    first = len(data.pool_images)
    input_pool = {c: torch.cat([index, torch.from_numpy(first + np.flatnonzero(view_classes == c))])
                  for c, index in data.input_pool.items()}
    no = torch.zeros(len(rows), dtype=torch.bool)
    return PairData(inputs=torch.cat([data.inputs, data.inputs[torch.from_numpy(rows)]]),
                    targets=torch.cat([data.targets, targets]),
                    classes=data.classes + [data.classes[i] for i in rows],
                    aligned=torch.cat([data.aligned, no]),
                    pool_images=torch.cat([data.pool_images, inputs]),
                    input_pool=input_pool,
                    fixed=torch.cat([data.fixed, no]))


def draw_batch(data: PairData, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of (input, target) uint8 images; class pairs get a fresh random input of their class
    (pixel and name pairs keep their own input)."""
    inputs, targets, _ = _draw(data, batch_size, generator)
    return inputs, targets


def _draw(data: PairData, batch_size: int, generator: torch.Generator,
          class_row_pairs: bool = False) -> tuple[torch.Tensor, torch.Tensor, list[int]]:
    """:func:`draw_batch` plus the pair index of each batch row. With ``class_row_pairs``, rows 2k and 2k+1
    are two pairs of one class (the second drawn among the pairs of the first's class)."""
    index = torch.randint(0, len(data.targets), (batch_size,), generator=generator)
    if class_row_pairs:
        by_class = data.pairs_by_class()
        for row in range(1, batch_size, 2):
            same = by_class[data.classes[int(index[row - 1])]]
            index[row] = same[torch.randint(0, len(same), (1,), generator=generator)]
    inputs = data.inputs[index]  # advanced indexing already copies
    for row, i in enumerate(index.tolist()):
        if not data.fixed[i]:
            pool = data.input_pool[data.classes[i]]
            if len(pool):
                inputs[row] = data.pool_images[pool[torch.randint(0, len(pool), (1,), generator=generator)]][0]
    return inputs, data.targets[index], index.tolist()


def prepare_batch(data: PairData, batch_size: int, noise: bool, sampler: torch.Generator,
                  device: torch.device = torch.device("cpu"),
                  conditioning: Conditioning | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """One training batch (condition, target) in [-1, 1] on ``device``: ``draw_batch``, scaling, (with
    ``noise``) random positioning, then ``conditioning``'s channels; every random draw from ``sampler``."""
    inputs, targets, index = _draw(data, batch_size, sampler)
    x, y = to_model_range(inputs).to(device), to_model_range(targets).to(device)
    if noise:
        x, y = random_positioning(x, y, sampler)
    if conditioning is not None and conditioning.kind != "none":
        x = conditioning.condition(x, conditioning.labels([data.classes[i] for i in index]))
    return x, y


def prepare_class_batch(data: PairData, batch_size: int, noise: bool, sampler: torch.Generator,
                        device: torch.device, conditioning: Conditioning,
                        class_names: tuple[str, ...]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A batch for the class_gan objective: as :func:`prepare_batch`, with rows (2k, 2k+1) two inputs of one
    class, plus each row's class index in ``class_names``. Random positioning moves input and target apart
    (they are not partners)."""
    inputs, targets, index = _draw(data, batch_size, sampler, class_row_pairs=True)
    x, y = to_model_range(inputs).to(device), to_model_range(targets).to(device)
    if noise:
        x, _ = random_positioning(x, x, sampler)
        y, _ = random_positioning(y, y, sampler)
    names = [data.classes[i] for i in index]
    if conditioning.kind != "none":
        x = conditioning.condition(x, conditioning.labels(names))
    position = {name: i for i, name in enumerate(class_names)}
    return x, y, torch.tensor([position[name] for name in names], dtype=torch.int64)


def resolve_objective(setting: str, data: PairData) -> tuple[str, str]:
    """``translation.objective`` for this model's training pairs, and why: ``auto`` gives ``class_gan`` when
    no training pair is a pixel or name pair (every target is a random image of the input's class), else
    ``pix2pix``; 'pix2pix' and 'class_gan' are taken as set."""
    fixed, total = int(data.fixed.sum()), len(data.fixed)
    if setting != "auto":
        return setting, "as set"
    if fixed:
        return "pix2pix", f"auto: {fixed} of {total} training pairs are pixel or name pairs"
    return "class_gan", (f"auto: all {total} training pairs are class pairs, whose pixel loss would pull every "
                         f"output to its class mean")


def resolve_conditioning(setting: str, objective: str, classes: int) -> str:
    """The conditioning kind one model of ``classes`` classes trains with: ``translation.conditioning``'s value for
    its direction, where ``auto`` is ``inferred`` under the class-pair objective (the generator is told the class a
    reader reads from its input, never the input's own class: pixel-free training has nothing else to tie an output
    to its input's class) and ``none`` under pix2pix, whose partner image already does that, or for one class."""
    if setting != "auto":
        return setting
    return "inferred" if objective == "class_gan" and classes > 1 else "none"


def objective_settings(settings: dict, translation: dict, objective: str, direction: str | None = None) -> dict:
    """The preset block with the class_gan keys of ``translation.class_gan`` added when that objective
    trains (the pix2pix settings stay exactly the preset's); a key given per direction ({v2t: w, t2v: w}, as
    ``nce`` is) takes ``direction``'s value. ``class_gan.iterations`` replaces the preset's iterations where
    it is not null; ``class_gan.lr_decay`` 0, ``latent_map`` false, ``inject_every_level`` false, ``decoder_noise`` 0, ``output_grain`` false, ``select_every`` 0,
    ``mode_seeking_per_pair`` false, ``fixed_pattern`` 0, ``fixed_sign`` 0, ``shared_detail`` 0, ``d_antialias`` false, ``statistics_spectrum`` true, ``statistics_pool`` 1, ``views`` 1, ``pack`` 1 and ``nearest`` 0 (with its ``nearest_draws``) add no key."""
    if objective != "class_gan":
        return settings
    if settings["batch_size"] < 2 or settings["batch_size"] % 2:
        raise ValueError(f"the class_gan objective pairs the rows of a batch: batch_size must be even and >= 2, "
                         f"got {settings['batch_size']} (presets.{translation['preset']}.batch_size)")
    terms = dict(translation["class_gan"])
    for key, value in terms.items():
        if isinstance(value, dict):
            if direction not in value:
                raise ValueError(f"translation.class_gan.{key} is given per direction ({', '.join(value)}): "
                                 f"name the direction to train, got {direction!r}")
            terms[key] = value[direction]
    if terms.get("skips") == "all":
        terms["skips"] = None  # the generator's own spelling of every skip connection
    iterations = terms.pop("iterations", None)
    if iterations is not None:
        terms["iterations"] = iterations
    for switch in ("lr_decay", "latent_map", "inject_every_level", "decoder_noise", "output_grain", "select_every",
                   "mode_seeking_per_pair", "fixed_pattern", "fixed_sign", "shared_detail", "d_antialias"):
        if not terms.get(switch):
            terms.pop(switch, None)  # off adds no key: the settings, and the checkpoints hashed from them, stay as they were
    if terms.get("statistics_spectrum", True) is True:
        terms.pop("statistics_spectrum", None)  # the statistics term as it always was: no key
    if not terms.get("nearest"):
        terms.pop("nearest", None)
        terms.pop("nearest_draws", None)
    for neutral in ("views", "pack", "statistics_pool"):
        if terms.get(neutral) == 1:
            terms.pop(neutral)  # the centre tile alone, one image per judgement, contrast per pixel: the same
    return dict(settings, objective="class_gan", **terms)


def output_settings(settings: dict, translation: dict, targets: torch.Tensor) -> tuple[dict, str]:
    """``settings`` with ``grey_output: true`` when ``translation.grey_output`` is auto and every training target is
    grey (:func:`grey_targets`), so the generator draws one channel, repeated; otherwise unchanged (no key, so the
    checkpoints hashed from them stay as they were). Also the phrase the training line prints."""
    if translation["grey_output"] == "auto" and grey_targets(targets):
        return dict(settings, grey_output=True), f", grey output (all {len(targets)} training targets have R = G = B)"
    return settings, ""


def validation_l1(generator: torch.nn.Module, validation: PairData, batch_size: int = 32,
                  conditioning: Conditioning | None = None) -> float:
    """Mean |G(x) - y| on [-1, 1] over the aligned validation pairs, in eval mode (no dropout, running BN);
    ``x`` carries ``conditioning``'s channels."""
    device = next(generator.parameters()).device
    keep = validation.aligned.nonzero().flatten()
    was_training = generator.training
    generator.eval()
    total = 0.0
    codes = fixed_codes(generator, len(keep))
    with torch.no_grad():
        for start in range(0, len(keep), batch_size):
            index = keep[start:start + batch_size]
            x = to_model_range(validation.inputs[index]).to(device)
            y = to_model_range(validation.targets[index]).to(device)
            if conditioning is not None and conditioning.kind != "none":
                x = conditioning.condition(x, conditioning.labels([validation.classes[i] for i in index.tolist()]))
            z = None if codes is None else codes[start:start + batch_size].to(device)
            total += float((generator(x, z).float() - y).abs().mean(dim=(1, 2, 3)).sum())
    generator.train(was_training)
    return total / len(keep)


def class_paired(validation: PairData) -> list[str]:
    """The sorted class names of ``validation`` with no aligned pair: scored without Colour-SSIM
    (:func:`validation_by_class`), by the judge where there is one."""
    classes, aligned = np.array(validation.classes), validation.aligned.numpy()
    return [name for name in sorted(set(validation.classes)) if not (aligned & (classes == name)).any()]


@torch.no_grad()
def validation_by_class(generator: torch.nn.Module, validation: PairData, conditioning: Conditioning | None = None,
                        batch_size: int = 32, judge: Referee | None = None) -> dict[str, float]:
    """Per class, a validation quality where higher is better, in eval mode: the mean aligned Colour-SSIM
    (Wang et al. 2004, 255 range) over the class's aligned validation pairs. For a class without aligned pairs,
    with r the within-class spread ratio of :func:`spread_ratio` (0 for a collapsed class):

    - with a ``judge``: the mean probability its real-only classifier of the target modality gives the class for
      the class's translated validation inputs (:meth:`Referee.recognition`: is the output recognisable as its
      input's class) minus the collapse gap max(0, 1 - 2r) (0 from half the real spread on, issue 24's bar;
      spreading more is left to the classifier, which does not recognise noise);
    - without: minus the mean over channels of |mean_gen - mean_real| + |std_gen - std_real| of the generated and
      real validation targets (pixel values in [0, 1]: colour and contrast), minus the spread gap min(1, |1 - r|)."""
    device = next(generator.parameters()).device
    was_training = generator.training
    generator.eval()
    outputs, codes = [], fixed_codes(generator, len(validation.inputs))
    for start in range(0, len(validation.inputs), batch_size):
        x = to_model_range(validation.inputs[start:start + batch_size]).to(device)
        if conditioning is not None and conditioning.kind != "none":
            x = conditioning.condition(x, conditioning.labels(validation.classes[start:start + batch_size]))
        z = None if codes is None else codes[start:start + batch_size].to(device)
        outputs.append(to_uint8(generator(x, z)).cpu())
    generator.train(was_training)
    made = torch.cat(outputs)
    classes = np.array(validation.classes)
    aligned = validation.aligned.numpy()
    unaligned = set(class_paired(validation))
    scores = {}
    for name in sorted(set(validation.classes)):
        rows = classes == name
        if name not in unaligned:
            keep = torch.from_numpy(rows & aligned)
            scores[name] = float(colour_ssim(made[keep].permute(0, 2, 3, 1).numpy(),
                                             validation.targets[keep].permute(0, 2, 3, 1).numpy(), 255.0).mean())
        else:
            keep = torch.from_numpy(rows)
            spread = spread_ratio(made[keep], validation.targets[keep])
            if judge is not None:
                recognised = float(judge.recognition(made[keep], [name] * int(keep.sum())).mean())
                scores[name] = recognised - max(0.0, 1.0 - 2.0 * spread)
            else:
                a, b = made[keep].double() / 255, validation.targets[keep].double() / 255
                gap = (a.mean(dim=(0, 2, 3)) - b.mean(dim=(0, 2, 3))).abs() + (a.std(dim=(0, 2, 3)) - b.std(dim=(0, 2, 3))).abs()
                scores[name] = -float(gap.mean()) - min(1.0, abs(1.0 - spread))
    return scores


def spread_ratio(generated: torch.Tensor, real: torch.Tensor, side: int = 64) -> float:
    """Mean pairwise L1 distance among ``generated`` over the same among ``real`` (uint8 N x 3 x S x S), on
    ``side`` px grey images in [0, 1] (64: the score stage's pixel view of diversity): 1 when generated images vary as much as real ones, 0 when they
    are all one image (collapse). 1.0 when either set has fewer than 2 images or the real ones are identical."""
    def spread(images: torch.Tensor) -> float:
        grey = F.interpolate(images.float().mean(dim=1, keepdim=True) / 255, size=(side, side), mode="area")
        rows = grey.reshape(len(images), -1).double()
        return float(torch.cdist(rows, rows, p=1).sum()) / (len(rows) * (len(rows) - 1))

    if len(generated) < 2 or len(real) < 2:
        return 1.0
    real_spread = spread(real)
    return spread(generated) / real_spread if real_spread > 0 else 1.0


def settled_classes(history: list[dict], tolerance: float, patience: int,
                    floor: dict[str, float] | None = None) -> dict[str, int | None]:
    """Early stopping per class from the ``val_by_class`` rows of ``history``.

    A class has settled once its best score has risen by at most ``tolerance`` over its last ``patience``
    evaluations and the mean of those ``patience`` scores has reached its ``floor`` (if given:
    :func:`recognition_floor`; a class not yet learnt cannot have settled on a plateau, and one lucky validation
    of a few images does not clear the floor for it); its value is then the first step whose score came within
    ``tolerance`` of that best (what the class needed), else None (still improving, or below its floor)."""
    rows = [r for r in history if "val_by_class" in r]
    floor = floor or {}
    settled: dict[str, int | None] = {}
    for name in (rows[-1]["val_by_class"] if rows else {}):
        scores = [r["val_by_class"][name] for r in rows]
        best = np.maximum.accumulate(scores)
        if (len(scores) > patience and best[-1] - best[-1 - patience] <= tolerance
                and np.mean(scores[-patience:]) >= floor.get(name, -np.inf)):
            settled[name] = next(r["step"] for r, v in zip(rows, scores) if v >= best[-1] - tolerance)
        else:
            settled[name] = None
    return settled


def recognition_floor(judge: Referee, validation: PairData) -> dict[str, float]:
    """Per class without aligned validation pairs, the score it must reach before it can settle under a
    ``judge`` (:func:`settled_classes`): min(1/K, r/2), K the judge's classes and r the mean probability the
    judge gives the class for its real validation targets (:meth:`Referee.recognition`). Chance is the bar for
    "learnt something"; half the real images' own recognition lowers it for a class the judge barely knows."""
    classes = np.array(validation.classes)
    floor = {}
    for name in class_paired(validation):
        rows = classes == name
        real = float(judge.recognition(validation.targets[torch.from_numpy(rows)], [name] * int(rows.sum())).mean())
        floor[name] = min(1.0 / len(judge.class_names), real / 2)
    return floor


def all_settled(history: list[dict], tolerance: float, patience: int, floor: dict[str, float] | None = None) -> bool:
    """True when every class of :func:`settled_classes` has settled (False before any evaluation)."""
    settled = settled_classes(history, tolerance, patience, floor)
    return bool(settled) and all(v is not None for v in settled.values())


@dataclass
class TrainResult:
    generator: torch.nn.Module
    history: list[dict]
    steps: int
    seconds: float
    resumed_from: int
    device: str
    precision: str = "fp32"
    precision_reason: str = "as set"
    selected: dict | None = None  # class_gan.select_every: {step, val_fid} of the snapshot returned, else None


@dataclass(frozen=True)
class Job:
    """What stays fixed during one ``train_translator`` call."""

    label: str  # direction/scope
    settings: dict
    run: dict
    device: torch.device
    checkpoint: Path | None
    keys: dict
    validation: PairData | None
    conditioning: Conditioning
    eval_every: int | None = None  # steps between per-class validations (capacity auto), else None
    stop: object = None  # callable(history) -> bool, checked after each per-class validation
    class_names: tuple[str, ...] = ()  # the class_gan objective's class index (sorted training classes)
    guide: torch.nn.Module | None = None  # class_gan.semantic's target-modality classifier (build_guide)
    referee: Referee | None = None  # class_gan.select_every's judge of snapshots (build_referee)
    judge: Referee | None = None  # capacity auto's reader of class-paired validation outputs (build_judge)

    @property
    def class_gan(self) -> bool:
        return self.settings.get("objective") == "class_gan"

    def evaluates_at(self, step: int) -> bool:
        return bool(self.eval_every) and self.validation is not None and (
            step % self.eval_every == 0 or step == self.settings["iterations"])

    def selects_at(self, step: int) -> bool:
        """Steps where ``class_gan.select_every`` scores the output generator: every that many steps, and the last."""
        every = self.settings.get("select_every") or 0
        return self.referee is not None and every > 0 and (step % every == 0 or step == self.settings["iterations"])

    def remedy(self) -> str:
        return f"lower presets.{self.run.get('preset') or '<preset>'}.lr (now {self.settings['lr']:g})"


@dataclass
class RunState:
    """What a checkpoint stores besides the networks: step, logged rows, seconds trained before this call, and
    the divergence baselines measured at step 0 (generator weight norm, validation L1 or None), and the
    snapshot ``class_gan.select_every`` keeps: {step, val_fid, generator (state dict)} or None."""

    step: int = 0
    history: list[dict] = field(default_factory=list)
    seconds_before: float = 0.0
    baseline: dict = field(default_factory=dict)
    resumed_from: int = 0
    saved_step: int | None = None
    selected: dict | None = None

    def last_good(self, path: Path | None) -> str:
        if self.saved_step is None:
            return "no checkpoint was written"
        return f"last good checkpoint: {path} (step {self.saved_step})"


# ---------------------------------------------------------------- resume

def checkpoint_keys(settings: dict, run: dict, direction: str, scope: str, data: PairData,
                    conditioning: Conditioning | None = None, judged: bool = False) -> dict:
    """The three things a checkpoint must match to be resumed, each a SHA-256: ``params`` (the preset without
    ``iterations``, seed, precision, direction, scope, conditioning kind and classes; ``judged``: the per-class
    validations read class-paired outputs with a judge, see :func:`validation_by_class`), ``data``
    (:meth:`PairData.fingerprint`, which covers the reference images, taken from the training targets) and
    ``code`` (every vtgen source file this stage runs)."""
    conditioning = conditioning or Conditioning()
    params = {"settings": {k: v for k, v in settings.items() if k != "iterations"}, "seed": run["seed"],
              "precision": run["precision"], "direction": direction, "scope": scope,
              "conditioning": [conditioning.kind, list(conditioning.classes)]}
    if judged:
        params["validation_by_class"] = "recognition"
    return {"params": hashlib.sha256(json.dumps(params, sort_keys=True).encode()).hexdigest(),
            "data": data.fingerprint(), "code": code_fingerprint("vtgen.stages.train")}


def resume_decision(saved: dict, keys: dict, iterations: int, path: Path | str) -> str | None:
    """None when checkpoint ``saved`` (at ``path``) can be resumed for a run of ``iterations`` steps, else why not.

    Resumable: all of :func:`checkpoint_keys` match and its step is at most ``iterations``. At ``iterations`` the
    run is finished, and since training is deterministic (same params, data and code, same weights; to the bit on
    the CPU) its checkpoint is the result training again would give: nothing is trained again (after a kill
    between the last step and the written model, or a rerun of an upstream stage that wrote the same data). Past
    ``iterations`` (a shorter run asked for) it starts afresh."""
    stored = saved.get("fingerprint")
    if not isinstance(stored, dict):
        return f"{path} was written by an older vtgen (no code fingerprint)"
    changed = [CHANGED[k] for k in CHANGED if stored.get(k) != keys[k]]
    if changed:
        return f"{' and '.join(changed)} changed since {path}" if len(changed) < 3 else \
            f"{', '.join(changed[:2])} and {changed[2]} changed since {path}"
    if saved["step"] > iterations:
        return f"{path} is at step {saved['step']}, past the {iterations} iterations the run asks for"
    return None


def _set_aside(path: Path, label: str, problem: str) -> None:
    """Rename an unusable checkpoint to ``<name>.stale`` and say so in one line."""
    stale = path.with_name(path.name + STALE_SUFFIX)
    path.replace(stale)
    print(f"train {label}: cannot resume from {path} ({problem}); set it aside as {stale}; training afresh")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0] if text else ''}"


def _read_checkpoint(path: Path, label: str) -> dict | None:
    """The checkpoint at ``path``, or None after setting aside one that is unreadable or lacks fields."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - torch raises zip, pickle, EOF and runtime errors alike
        _set_aside(path, label, f"unreadable, {_first_line(exc)}")
        return None
    missing = [k for k in CHECKPOINT_FIELDS if not isinstance(state, dict) or k not in state]
    if missing:
        _set_aside(path, label, f"not a checkpoint of this vtgen version, missing {', '.join(missing)}")
        return None
    return state


def _restore(training: TranslatorTraining, sampler: torch.Generator, state: dict) -> None:
    """Networks, optimisers and every random generator as they were at the checkpoint."""
    training.load_state_dict(state)
    sampler.set_state(state["sampler_rng"])
    torch.set_rng_state(state["torch_rng"])
    if training.device.type == "cuda" and state.get("cuda_rng") is not None:
        torch.cuda.set_rng_state(state["cuda_rng"])


def _fresh(job: Job) -> tuple[TranslatorTraining, torch.Generator]:
    """Networks and batch sampler at step 0, both seeded with ``translation.seed``."""
    torch.manual_seed(job.run["seed"])
    sampler = torch.Generator().manual_seed(job.run["seed"])
    return TranslatorTraining(job.settings, job.device, job.run["precision"],
                              3 + job.conditioning.extra_channels, len(job.class_names), job.guide), sampler


def _baseline(training: TranslatorTraining, validation: PairData | None, conditioning: Conditioning) -> dict:
    """The untrained generator's weight norm and validation L1 (None without aligned validation pairs)."""
    val = validation_l1(training.generator, validation, conditioning=conditioning) \
        if validation is not None and bool(validation.aligned.any()) else None
    return {"weight_norm": training.generator_norm(), "val_l1": val}


def _start(job: Job) -> tuple[TranslatorTraining, torch.Generator, RunState]:
    """Resume from the job's checkpoint when :func:`resume_decision` allows it, else start afresh (saying why)."""
    training, sampler = _fresh(job)
    path = job.checkpoint
    saved = _read_checkpoint(path, job.label) if path and job.run["resume"] and path.is_file() else None
    reason = resume_decision(saved, job.keys, job.settings["iterations"], path) if saved is not None else None
    if saved is not None and reason is None:
        try:
            _restore(training, sampler, saved)
        except (KeyError, RuntimeError, ValueError, TypeError) as exc:
            _set_aside(path, job.label, f"does not fit these networks, {_first_line(exc)}")
            training, sampler = _fresh(job)
        else:
            finished = saved["step"] == job.settings["iterations"] or bool(job.stop and saved["history"]
                                                                           and job.stop(saved["history"]))
            print(f"train {job.label}: the finished run in {path} has the same params, data and code; its result is "
                  f"used, nothing is trained" if finished else
                  f"train {job.label}: resuming from step {saved['step']} ({path})")
            return training, sampler, RunState(saved["step"], saved["history"], saved["seconds"], saved["baseline"],
                                               resumed_from=saved["step"], saved_step=saved["step"],
                                               selected=saved.get("selected"))
    elif reason is not None:
        print(f"train {job.label}: {reason}; training afresh")
    return training, sampler, RunState(baseline=_baseline(training, job.validation, job.conditioning))


# ---------------------------------------------------------------- checkpoints

def _save_checkpoint(job: Job, training: TranslatorTraining, sampler: torch.Generator, state: RunState,
                     elapsed: float) -> None:
    """Write the checkpoint atomically; refuse (TrainingDiverged) when a network holds NaN or inf."""
    if job.checkpoint is None:
        return
    bad = _non_finite_tensors(training.generator, training.discriminator)
    if bad:
        raise TrainingDiverged(f"{job.label}: non-finite weights at step {state.step} ({_describe(bad)}); "
                               f"checkpoint not written; {state.last_good(job.checkpoint)}; {job.remedy()}")
    job.checkpoint.parent.mkdir(parents=True, exist_ok=True)
    save_atomic({"fingerprint": job.keys, "step": state.step, "history": state.history, "seconds": elapsed,
                 "baseline": state.baseline, "selected": state.selected, **training.state_dict(),
                 "sampler_rng": sampler.get_state(),
                 "torch_rng": torch.get_rng_state(),
                 "cuda_rng": torch.cuda.get_rng_state() if job.device.type == "cuda" else None}, job.checkpoint)
    state.saved_step = state.step


# ---------------------------------------------------------------- divergence guard

def _non_finite_tensors(*modules: torch.nn.Module) -> list[str]:
    """Names of the floating state tensors (weights, BatchNorm running statistics) holding NaN or inf."""
    return [f"{type(m).__name__}.{name}" for m in modules for name, t in m.state_dict().items()
            if t.is_floating_point() and not bool(torch.isfinite(t).all())]


def _describe(bad: list[str]) -> str:
    return ", ".join(bad[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")


def _check_finite(losses: torch.Tensor, job: Job, state: RunState) -> None:
    """Raise at the first step of the window (rows of ``losses``) with a NaN or infinite loss."""
    bad = (~torch.isfinite(losses).all(dim=1)).nonzero()
    if len(bad):
        row = int(bad[0])
        values = ", ".join(f"{n}={v:.4g}" for n, v in zip(LOSS_NAMES, losses[row].tolist()))
        raise TrainingDiverged(f"{job.label}: non-finite loss at step {state.step - len(losses) + row + 1} "
                               f"({values}); nothing after it was saved; {state.last_good(job.checkpoint)}; "
                               f"{job.remedy()}")


def _check_range(row: dict, training: TranslatorTraining, job: Job, state: RunState) -> None:
    """Raise when the generator's weight norm or a logged loss leaves its range (see the module docstring)."""
    def diverged(what: str) -> TrainingDiverged:
        return TrainingDiverged(f"{job.label}: diverged at step {row['step']}: {what}; "
                                f"{state.last_good(job.checkpoint)}; {job.remedy()}")

    norm, start = training.generator_norm(), state.baseline["weight_norm"]
    if not norm <= WEIGHT_GROWTH_LIMIT * start:
        raise diverged(f"generator weight norm {norm:.3g} is outside its range (at most {WEIGHT_GROWTH_LIMIT:g} x "
                       f"its step-0 value {start:.3g} = {WEIGHT_GROWTH_LIMIT * start:.3g})")
    for name in LOSS_NAMES:
        earlier = [r[name] for r in state.history]
        if earlier:
            limit = max(LOSS_FLOOR, LOSS_GROWTH_LIMIT * statistics.median(earlier))
            if row[name] > limit:
                raise diverged(f"{name} {row[name]:.3g} is outside its range (at most {limit:.3g}: "
                               f"{LOSS_GROWTH_LIMIT:g} x the median of earlier windows, at least {LOSS_FLOOR:g})")


def _check_validation(row: dict, job: Job, state: RunState) -> None:
    """Raise when the final validation L1 is clearly worse than the untrained generator's (runs of at least
    ``MIN_VAL_CHECK_STEPS``: before that, eval mode normalises with mostly initial running statistics)."""
    start = state.baseline.get("val_l1")
    final = row["step"] == job.settings["iterations"] and row["step"] >= MIN_VAL_CHECK_STEPS
    if start is None or "val_l1" not in row or not final:
        return
    limit = max(VAL_WORSE_FACTOR * start, start + VAL_WORSE_MARGIN)
    if not row["val_l1"] <= limit:
        raise TrainingDiverged(f"{job.label}: diverged by step {row['step']}: validation L1 {row['val_l1']:.3g} is "
                               f"worse than the untrained generator's {start:.3g} (limit {limit:.3g}); "
                               f"{job.remedy()} or train longer")


# ---------------------------------------------------------------- logging and progress

def _logs_at(step: int, job: Job) -> bool:
    run = job.run
    return (step % run["log_every"] == 0 or step % run["checkpoint_every"] == 0 or step == job.settings["iterations"]
            or job.evaluates_at(step) or job.selects_at(step))


def _checkpoints_at(step: int, job: Job) -> bool:
    """Checkpoint steps: every checkpoint_every, the last, and every per-class validation (so a resumed run
    sees the history its early-stopping decision was made on), and every snapshot selection (likewise)."""
    return (step % job.run["checkpoint_every"] == 0 or step == job.settings["iterations"] or job.evaluates_at(step)
            or job.selects_at(step))


def _window_row(losses: torch.Tensor, training: TranslatorTraining, job: Job, state: RunState,
                session_seconds: float) -> dict:
    """The logged row of a window: mean losses, images per second in this call, ``val_l1`` at checkpoints."""
    images = (state.step - state.resumed_from) * job.settings["batch_size"]
    row = {"step": state.step, **dict(zip(LOSS_NAMES, losses.mean(dim=0).tolist())),
           "images_per_s": images / max(session_seconds, 1e-9)}
    if _checkpoints_at(state.step, job) and job.validation is not None and bool(job.validation.aligned.any()):
        row["val_l1"] = validation_l1(training.output_generator, job.validation, conditioning=job.conditioning)
    if job.evaluates_at(state.step):
        row["val_by_class"] = validation_by_class(training.output_generator, job.validation, job.conditioning,
                                                  judge=job.judge)
    if job.selects_at(state.step):
        row["val_fid"] = job.referee.score(training.output_generator, job.conditioning)
    return row


def _select(row: dict, training: TranslatorTraining, state: RunState) -> None:
    """Keep a copy of the output generator when the row's validation FID is the lowest so far (ties: the earlier)."""
    if "val_fid" in row and (state.selected is None or row["val_fid"] < state.selected["val_fid"]):
        weights = {k: v.detach().cpu().clone() for k, v in training.output_generator.state_dict().items()}
        state.selected = {"step": row["step"], "val_fid": row["val_fid"], "generator": weights}


def _progress_bar(job: Job, initial: int, show: bool) -> tqdm:
    return tqdm(total=job.settings["iterations"], initial=initial, desc=f"train {job.label}", unit="it",
                disable=not show, mininterval=1.0, dynamic_ncols=True)


def _show(bar: tqdm, row: dict) -> None:
    bar.set_postfix({"D": f"{row['loss_d']:.3f}", "G": f"{row['loss_g_gan']:.3f}", "L1": f"{row['loss_g_l1']:.3f}",
                     "img/s": f"{row['images_per_s']:.0f}"}, refresh=False)


def _end_window(window: list[torch.Tensor], training: TranslatorTraining, sampler: torch.Generator, job: Job,
                state: RunState, started: float) -> dict:
    """Close a logging window (the loop's host syncs all happen here): check it, build its row, record it,
    checkpoint if due."""
    losses = torch.stack(window).float().cpu()
    _check_finite(losses, job, state)
    session = time.perf_counter() - started
    row = _window_row(losses, training, job, state, session)
    _check_range(row, training, job, state)
    _check_validation(row, job, state)
    _select(row, training, state)
    state.history.append(row)
    if _checkpoints_at(state.step, job):
        _save_checkpoint(job, training, sampler, state, state.seconds_before + session)
    return row


# ---------------------------------------------------------------- the loop

def train_translator(data: PairData, settings: dict, run: dict, direction: str, scope: str,
                     checkpoint_dir: Path | None = None, on_log=None, progress: bool = True,
                     validation: PairData | None = None, conditioning: Conditioning | None = None,
                     eval_every: int | None = None, stop=None, label: str | None = None,
                     guide: torch.nn.Module | None = None, referee: Referee | None = None,
                     judge: Referee | None = None) -> TrainResult:
    """Train one conditional GAN on ``data`` for ``settings['iterations']`` steps of :class:`TranslatorTraining`.

    ``settings`` is a presets block (its keys plus batch_size, iterations, noise); ``run`` holds device,
    precision, threads, checkpoint_every, resume, log_every and seed. Losses are averaged over each
    ``log_every`` window and passed to ``on_log(row)``; at each checkpoint the row also holds ``val_l1``, the
    L1 error on the aligned pairs of ``validation``. ``conditioning`` (default none) adds its channels to
    every generator input. With ``eval_every``, every that many steps the row also holds ``val_by_class``
    (:func:`validation_by_class`) and training ends early once ``stop(history)`` is true (early stopping).
    ``guide`` is the classifier ``class_gan.semantic`` needs (:func:`build_guide`). With ``referee`` and
    ``class_gan.select_every`` n > 0, every n steps and at the last the row holds ``val_fid`` (:meth:`Referee.score`)
    and the run returns the snapshot with the lowest (its step and value in ``TrainResult.selected``).
    ``judge`` scores the per-class validations of class-paired outputs (:func:`validation_by_class`).
    A non-finite or out-of-range loss or weight raises
    TrainingDiverged naming the step, the quantity and the last good checkpoint.
    """
    device = resolve_device(run["device"])
    precision, precision_reason = resolve_precision(run["precision"], device)
    run = dict(run, precision=precision)
    if device.type == "cpu":
        torch.set_num_threads(run["threads"])
    job = Job(f"{direction}/{scope}{f' ({label})' if label else ''}", settings, run, device,
              Path(checkpoint_dir) / CHECKPOINT_NAME if checkpoint_dir else None,
              checkpoint_keys(settings, run, direction, scope, data, conditioning, judge is not None), validation,
              conditioning or Conditioning(), eval_every, stop, tuple(sorted(set(data.classes))), guide, referee,
              judge)
    training, sampler, state = _start(job)
    for row in state.history:  # a resumed run logs the rows it inherits again, so the log is whole
        if on_log:
            on_log(row)
    window, started = [], time.perf_counter()
    with _progress_bar(job, state.step, progress) as bar:
        stopped = bool(stop and state.history and stop(state.history))
        while state.step < settings["iterations"] and not stopped:
            if job.class_gan:
                batch = prepare_class_batch(data, settings["batch_size"], settings["noise"], sampler, device,
                                            job.conditioning, job.class_names)
            else:
                batch = prepare_batch(data, settings["batch_size"], settings["noise"], sampler, device, job.conditioning)
            training.schedule_learning_rate(state.step, settings["iterations"])
            window.append(torch.stack(list(training.step(*batch).values())))
            state.step += 1
            if _logs_at(state.step, job):
                row = _end_window(window, training, sampler, job, state, started)
                window = []
                stopped = bool(stop and "val_by_class" in row and stop(state.history))
                if on_log:
                    on_log(row)
                _show(bar, row)
            bar.update(1)
    bad = _non_finite_tensors(training.output_generator)
    if bad:
        raise TrainingDiverged(f"{job.label}: non-finite generator weights at step {state.step} ({_describe(bad)}); "
                               f"{state.last_good(job.checkpoint)}; {job.remedy()}")
    seconds = state.seconds_before + time.perf_counter() - started
    generator = training.output_generator
    if state.selected is not None:
        generator.load_state_dict(state.selected["generator"])
    selected = None if state.selected is None else {k: state.selected[k] for k in ("step", "val_fid")}
    return TrainResult(generator.cpu(), state.history, state.step, seconds, state.resumed_from, str(device),
                       precision, precision_reason, selected)


def _live_logger(folder: Path):
    """A dvclive ``Live`` writing into ``folder`` and the ``on_log`` callback feeding it (train/<loss>, val/l1)."""
    from dvclive import Live
    from scmrepo.exceptions import SCMError

    try:
        live = Live(dir=str(folder), save_dvc_exp=False, dvcyaml=None, report=None)
    except SCMError as exc:  # dvclive reads the Git revision of the DVC project it runs in
        raise RuntimeError(f"dvclive cannot log in this Git repository ({exc}); "
                           f"make a first commit (`git commit`) and run again") from exc

    def log(row: dict) -> None:
        live.step = row["step"]
        for name in LOSS_NAMES:  # not images_per_s, a time (timing.json has the seconds per step)
            live.log_metric(f"train/{name}", row[name])
        if "val_l1" in row:
            live.log_metric("val/l1", row["val_l1"])

    return live, log


def train_capacity_auto(data: PairData, validation: PairData, settings: dict, run: dict, direction: str, scope: str,
                        checkpoint_dir: Path | None = None, on_log=None, progress: bool = True,
                        conditioning: Conditioning | None = None, guide: torch.nn.Module | None = None,
                        referee: Referee | None = None, judge: Referee | None = None) -> tuple[TrainResult, dict, dict]:
    """``translation.capacity: auto``: the smallest width and fewest iterations that reach the largest width's
    validation quality, per class, for one model.

    1. Width probe: every width of ``capacity.widths`` (ngf = ndf) trains ``probe_iterations`` steps; per class,
       the width needed is the smallest whose :func:`validation_by_class` score is within ``tolerance`` of the
       largest width's. The model takes the largest width any class needs.
    2. Early stopping: that width's probe run continues (from its checkpoint) up to the preset's iterations,
       validated per class every ``eval_every`` steps, and stops once every class has settled
       (:func:`settled_classes`: its best rose by at most ``tolerance`` over ``patience`` validations and, scored
       by a ``judge``, their mean reached :func:`recognition_floor`); with ``referee``, this continuation selects its
       snapshot as :func:`train_translator` says.

    Returns (the result, the settings of the chosen model, the ``capacity`` record of train.json: per class the
    width needed and the step it settled at, and the compute - GFLOP from :func:`training_step_flops` and
    seconds - against the fixed large model, the largest width trained for the preset's iterations).
    """
    cap = run["capacity"]
    widths, tolerance, patience = sorted(cap["widths"]), cap["tolerance"], cap["patience"]
    probe_steps = min(cap["probe_iterations"], settings["iterations"])
    extra = (conditioning or Conditioning()).extra_channels
    at = {w: dict(settings, ngf=w, ndf=w) for w in widths}
    folder = (lambda w: Path(checkpoint_dir) / f"width_{w}") if checkpoint_dir else (lambda w: None)
    probes, results = {}, {}
    for width in widths:
        done = None if probe_steps >= settings["iterations"] else _finished_probe(
            folder(width), dict(at[width], iterations=probe_steps), run, direction, scope, data, conditioning,
            judge is not None)
        if done is not None:  # a rerun: this probe finished before (its run may have gone on since)
            print(f"train {direction}/{scope}: width probe {width} taken from its checkpoint")
            probes[width] = done
            continue
        result = train_translator(data, dict(at[width], iterations=probe_steps), run, direction, scope, folder(width),
                                  progress=progress, validation=validation, conditioning=conditioning,
                                  eval_every=cap["eval_every"], label=f"width probe {width}", guide=guide,
                                  judge=judge)
        probes[width] = {"val_by_class": result.history[-1]["val_by_class"], "seconds": round(result.seconds, 2)}
        results[width] = result
    reference = probes[widths[-1]]["val_by_class"]
    needed = {name: next(w for w in widths if probes[w]["val_by_class"][name] >= reference[name] - tolerance)
              for name in reference}
    chosen = max(needed.values())
    floor = recognition_floor(judge, validation) if judge is not None else {}
    if floor:
        print(f"train {direction}/{scope}: a class scored by recognition settles only from its floor up (chance "
              f"{1 / len(judge.class_names):.3f}, or half its real images' score): "
              + ", ".join(f"{name} {value:.3f}" for name, value in floor.items()))
    final = results[chosen] if probe_steps >= settings["iterations"] else train_translator(
                             data, at[chosen], dict(run, resume=True), direction, scope, folder(chosen),
                             on_log=on_log, progress=progress, validation=validation, conditioning=conditioning,
                             eval_every=cap["eval_every"], stop=lambda history: all_settled(history, tolerance, patience, floor),
                             label=f"width {chosen}, early stopping", guide=guide, referee=referee, judge=judge)
    if chosen in results and final is not results[chosen] and final.resumed_from == probe_steps:
        final.resumed_from = results[chosen].resumed_from  # continuing this call's own probe is not a resume
    settled = settled_classes(final.history, tolerance, patience, floor)
    flops = {w: training_step_flops(at[w], 3 + extra, guide=guide) for w in widths}
    actual = sum(probe_steps * flops[w] for w in widths if w != chosen) + final.steps * flops[chosen]
    fixed = settings["iterations"] * flops[widths[-1]]
    seconds = sum(p["seconds"] for w, p in probes.items() if w != chosen) + final.seconds
    fixed_seconds = probes[widths[-1]]["seconds"] / probe_steps * settings["iterations"]
    record = {
        "mode": "auto", "widths": widths, "probe_iterations": probe_steps, "eval_every": cap["eval_every"],
        "tolerance": tolerance, "patience": patience,
        "metric": "validation Colour-SSIM per class (aligned pairs); for class pairs " + (
            "a real-only target classifier's mean probability of the class minus the collapse gap, settling only "
            "from min(chance, half its real images' probability) up"
            if judge is not None else "minus colour and contrast gaps and the within-class spread gap") +
            " (validation_by_class)",
        "probe": {str(w): p for w, p in probes.items()}, "chosen_width": chosen, "steps": final.steps,
        "max_iterations": settings["iterations"], "stopped_early": final.steps < settings["iterations"],
        "per_class": {name: {"width_needed": needed[name], "settled_at_step": settled.get(name),
                              **({"floor": round(floor[name], 4)} if name in floor else {})} for name in needed},
        "compute": {"gflop_per_step": {str(w): round(f / 1e9, 3) for w, f in flops.items()},
                    "gflop": round(actual / 1e9, 1), "fixed_large_gflop": round(fixed / 1e9, 1),
                    "saved_share": round(1 - actual / fixed, 3), "seconds": round(seconds, 1),
                    "fixed_large_seconds_estimate": round(fixed_seconds, 1),
                    "fixed_large": f"width {widths[-1]} for {settings['iterations']} iterations"},
    }
    return final, dict(at[chosen], iterations=final.steps), record


def _finished_probe(folder: Path | None, settings: dict, run: dict, direction: str, scope: str, data: PairData,
                    conditioning: Conditioning | None, judged: bool = False) -> dict | None:
    """The width probe's record (``val_by_class`` at step ``settings['iterations']``, seconds) from a checkpoint
    in ``folder`` that matches this run and has passed that step, or None (then the probe trains)."""
    path = folder / CHECKPOINT_NAME if folder else None
    if path is None or not run["resume"] or not path.is_file():
        return None
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - an unreadable checkpoint is dealt with by train_translator
        return None
    precision, _ = resolve_precision(run["precision"], resolve_device(run["device"]))
    keys = checkpoint_keys(settings, dict(run, precision=precision), direction, scope, data, conditioning, judged)
    steps = settings["iterations"]
    if not isinstance(saved, dict) or saved.get("fingerprint") != keys or saved.get("step", 0) < steps:
        return None
    row = next((r for r in saved["history"] if r["step"] == steps and "val_by_class" in r), None)
    return None if row is None else {"val_by_class": row["val_by_class"],
                                     "seconds": round(saved["seconds"] * steps / saved["step"], 2)}


def build_conditioning(kind: str, pairs: pd.DataFrame, scope: str, data: PairData,
                       classify: dict | None = None, seed: int = 0, epochs: int | None = None,
                       reader: str = "network") -> Conditioning:
    """The ``translation.conditioning`` of one model: its classes are those of the scope's pairs (sorted);
    a ``reference`` is the typical training target of each class (:func:`typical_images`); ``inferred``
    fits its input reader (``translation.inferred_reader``) on the training inputs of each class: ``network``
    trains the classify stage's classifier (``classify``: width, epochs, batch_size, lr; at the model's
    side) for ``epochs`` epochs (``translation.inferred_epochs``; None: classify's own), seeded with ``seed``;
    ``features`` fits :func:`vtgen.core.readers.fit_feature_reader` (no epochs, no seed)."""
    if kind == "none":
        return Conditioning()
    names = tuple(sorted(set(pairs_in(pairs, "train", scope)["class"])))
    references = typical_images(data.targets, data.classes, names) if kind == "reference" else None
    if kind != "inferred":
        return Conditioning(kind, names, references)
    if reader not in INPUT_READERS:
        raise ValueError(f"unknown translation.inferred_reader '{reader}' (allowed: {', '.join(INPUT_READERS)})")
    if classify is None and reader == "network":
        raise ValueError("conditioning 'inferred' needs the classify settings to train its input classifier")
    if len(names) < 2:
        raise ValueError(f"conditioning 'inferred' needs at least 2 classes to tell apart, the pairs have {list(names)}")
    index = torch.cat([data.input_pool[name] for name in names])
    labels = torch.cat([torch.full((len(data.input_pool[name]),), i, dtype=torch.int64) for i, name in enumerate(names)])
    images = data.pool_images[index]
    if reader == "features":
        started = time.perf_counter()
        model = fit_feature_reader(images, labels, len(names))
        with torch.no_grad():
            accuracy = float((model(images).argmax(dim=1) == labels).float().mean())
        print(f"conditioning inferred: hand-crafted-feature reader fitted on {len(images)} training inputs of "
              f"{len(names)} classes in {time.perf_counter() - started:.1f} s, training accuracy {accuracy:.3f}")
        return Conditioning(kind, names, classifier=model,
                            classifier_settings={"reader": "features", "size": int(images.shape[-1])})
    settings = {"size": int(images.shape[-1]), **{k: classify[k] for k in ("width", "epochs", "batch_size", "lr")}}
    if epochs is not None:
        settings["epochs"] = int(epochs)
    run = train_classifier(images, labels, images, labels, len(names), settings, seed)
    print(f"conditioning inferred: input classifier trained on {len(images)} training inputs of {len(names)} "
          f"classes ({settings['epochs']} epochs), training accuracy {run.test_accuracy[-1]:.3f}")
    return Conditioning(kind, names, classifier=run.model.eval(), classifier_settings=settings)


def build_guide(settings: dict, data: PairData, classify: dict, seed: int) -> torch.nn.Module | None:
    """The target-modality classifier of ``class_gan.semantic`` (None when that weight is 0 or the objective is not
    class_gan): the classify stage's network (``classify``: size, width, epochs, batch_size, lr) trained on the
    distinct training targets of each class (index = sorted class names, as the class_gan batches), seeded
    with ``seed`` + :data:`GUIDE_SEED_OFFSET`, so it is not any of the classifiers that score the outputs."""
    if settings.get("objective") != "class_gan" or not settings.get("semantic", 0.0):
        return None
    names = sorted(set(data.classes))
    if len(names) < 2:
        raise ValueError(f"class_gan.semantic needs at least 2 classes to tell apart, the pairs have {names}")
    rows = distinct_images(data.targets)  # class pairs repeat a target; keep one of each
    images = data.targets[rows]
    position = {name: i for i, name in enumerate(names)}
    labels = torch.tensor([position[data.classes[int(i)]] for i in rows], dtype=torch.int64)
    cfg = {"size": int(classify["size"]), **{k: classify[k] for k in ("width", "epochs", "batch_size", "lr")}}
    images = at_side(images, cfg["size"])
    run = train_classifier(images, labels, images, labels, len(names), cfg, seed + GUIDE_SEED_OFFSET)
    print(f"class_gan.semantic: target classifier trained on {len(images)} training targets of {len(names)} classes "
          f"({cfg['epochs']} epochs), training accuracy {run.test_accuracy[-1]:.3f}")
    return run.model.eval()


def _real_only_referee(data: PairData, validation: PairData, classify: dict, seed: int) -> Referee:
    """The real-only target classifier both ``select_every`` and capacity auto's ``recognition`` read with
    (:func:`vtgen.core.referee.train_referee` on the distinct training targets, seeded with ``seed`` +
    :data:`REFEREE_SEED_OFFSET`, its inputs the validation inputs): one seed, so the two are the same classifier."""
    return train_referee(data.targets, data.classes, validation.inputs, validation.classes, classify,
                         seed + REFEREE_SEED_OFFSET)


def training_sample(data: PairData, per_class: int, seed: int) -> tuple[torch.Tensor, list[str]]:
    """Up to ``per_class`` distinct training inputs of each class (``data.input_pool``, drawn with ``seed``) and
    their class names: what ``select_every`` translates when the pairs have no validation split."""
    sampler = torch.Generator().manual_seed(seed)
    rows, names = [], []
    for name in sorted(data.input_pool):
        pool = data.input_pool[name]
        picked = pool[torch.randperm(len(pool), generator=sampler)[:per_class]]
        rows.append(picked)
        names += [name] * len(picked)
    return data.pool_images[torch.cat(rows)] if rows else data.pool_images[:0], names


def build_referee(settings: dict, data: PairData, validation: PairData | None, classify: dict,
                  seed: int) -> Referee | None:
    """``class_gan.select_every``'s judge of snapshots (:func:`vtgen.core.referee.train_referee`: a classifier of
    the target modality trained on the distinct training targets, seeded with ``seed`` + :data:`REFEREE_SEED_OFFSET`,
    scoring the translated validation inputs, or without a validation split :func:`training_sample`'s training
    inputs: class pairs tie no input to a target, so the FID of translated training inputs still measures the
    outputs' distribution); None when the setting is 0 or absent, or with fewer than two classes to sample."""
    if not settings.get("select_every"):
        return None
    if validation is None:
        inputs, classes = training_sample(data, SELECTION_INPUTS_PER_CLASS, seed + REFEREE_SEED_OFFSET)
        if len(set(classes)) < 2:
            print(f"class_gan.select_every: {settings['select_every']} is set, but there is no validation split and "
                  f"fewer than two classes of training inputs to select by; the run keeps the last step's generator")
            return None
        referee = train_referee(data.targets, data.classes, inputs, classes, classify, seed + REFEREE_SEED_OFFSET)
        print(f"class_gan.select_every: no validation split; referee classifier trained on {len(referee.reference)} "
              f"training targets; every {settings['select_every']} steps the FID of {len(inputs)} translated "
              f"training inputs ({SELECTION_INPUTS_PER_CLASS} or fewer per class)")
        return referee
    referee = _real_only_referee(data, validation, classify, seed)
    print(f"class_gan.select_every: referee classifier trained on {len(referee.reference)} training targets; "
          f"every {settings['select_every']} steps the validation FID of {len(referee.inputs)} translated inputs")
    return referee


def build_judge(signal: str, data: PairData, validation: PairData, referee: Referee | None, classify: dict,
                seed: int) -> Referee | None:
    """Capacity auto's reader of class-paired validation outputs (``translation.capacity.class_signal``):
    for ``recognition``, when the validation split has a class without aligned pairs, the referee (a real-only
    classifier of the target modality, :func:`vtgen.core.referee.train_referee`; ``class_gan.select_every``'s
    when there is one, so it is trained once); else None (aligned classes are scored by Colour-SSIM)."""
    if signal != "recognition" or not class_paired(validation):
        return None
    if referee is not None:
        return referee
    judge = _real_only_referee(data, validation, classify, seed)
    print(f"capacity auto: classes without aligned validation pairs are scored by a real-only classifier of the "
          f"target modality (trained on {len(judge.reference)} training targets): its mean probability of the class")
    return judge


def selection_record(settings: dict, result: TrainResult, validation: PairData | None) -> dict:
    """What train.json says about ``class_gan.select_every``: which step's generator was kept and why."""
    every = settings.get("select_every") or 0
    if not every:
        return {"every": 0, "step": result.steps, "reason": "the last step's generator (class_gan.select_every 0)"}
    if result.selected is None:
        return {"every": every, "step": result.steps,
                "reason": "the last step's generator (nothing to select by, or no selection step was reached)"}
    scores = {r["step"]: round(r["val_fid"], 3) for r in result.history if "val_fid" in r}
    inputs = "validation inputs" if validation is not None else "training inputs (no validation split)"
    return {"every": every, "step": result.selected["step"], "val_fid": round(result.selected["val_fid"], 3),
            "val_fid_by_step": scores,
            "reason": f"the snapshot with the lowest classifier-view FID of its translated {inputs}"}


def _summary(result: TrainResult, data: PairData, validation: PairData | None, settings: dict, run: dict,
             direction: str, scope: str, conditioning: Conditioning) -> dict:
    """What ``train.json`` records about one training run."""
    final = result.history[-1] if result.history else {}
    reader = {} if conditioning.kind != "inferred" else {
        "input_reader": (conditioning.classifier_settings or {}).get("reader", "network")}
    return {
        "direction": direction, "scope": scope, "preset": run["preset"], "recipe": run["recipe"], "settings": settings, **reader,
        "conditioning": conditioning.kind, "conditioning_setting": run["conditioning"][direction],
        "classes": list(conditioning.classes),
        "precision": result.precision, "precision_setting": run["precision"],
        "precision_reason": result.precision_reason, "device": result.device, "threads": run["threads"], "seed": run["seed"],
        "training_pairs": len(data.targets), "aligned_pairs": int(data.aligned.sum()),
        "tile_size": int(data.targets.shape[-1]), "generator_parameters": count_parameters(result.generator),
        "steps": result.steps, "resumed_from_step": result.resumed_from, "wall_seconds": round(result.seconds, 2),
        "seconds_per_iteration": round(result.seconds / max(result.steps, 1), 5),
        "final_losses": {k: final.get(k) for k in LOSS_NAMES},
        "validation_pairs": 0 if validation is None else int(validation.aligned.sum()),
        "final_val_l1": final.get("val_l1"),
    }


def run_train(params: dict, direction: str, scope: str, pairs_dir: str | Path, out_dir: str | Path,
              checkpoint_root: str | Path = "checkpoints", progress: bool = True,
              tiles_path: str | Path = "data/roi/tiles.parquet") -> dict:
    """Stage entry: train ``direction`` for one ``scope`` entry and write ``out_dir`` atomically.

    ``out_dir`` receives generator.pt, train.json, dvclive/ (per-step losses) and timing.json (:data:`RUN_TIMES`:
    what the run took, kept out of train.json so that the same training writes the same files). ``tiles_path`` (the roi
    stage's table) is read only when ``class_gan.views`` asks for more crops of the training frames. Checkpoints
    live outside it, in ``checkpoint_root/<direction>/<scope>/``, because Snakemake and DVC
    delete a stage's outputs before rerunning it and a resume must survive that.
    """
    if direction not in DIRECTIONS:
        raise ValueError(f"unknown direction '{direction}' (allowed: {', '.join(DIRECTIONS)})")
    if scope not in params["translation"]["scope"]:
        raise ValueError(f"scope '{scope}' is not listed in translation.scope {params['translation']['scope']}")
    settings, run = model_settings(params), params["translation"]
    pairs_dir = Path(pairs_dir)
    pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    if pairs.empty:
        return _not_applicable(pairs_dir, direction, scope, Path(out_dir))
    data = load_pair_data(pairs, splits, direction, scope, settings["size"])
    validation = (load_pair_data(pairs, splits, direction, scope, settings["size"], split="val")
                  if not pairs_in(pairs, "val", scope).empty else None)
    settings = check_training_fits(settings, len(data.targets), f"presets.{run['preset']}", f"train {direction}/{scope}",
                                   resolve_device(run["device"]).type)
    objective, objective_reason = resolve_objective(run["objective"], data)
    conditioning_kind = resolve_conditioning(run["conditioning"][direction], objective,
                                             pairs_in(pairs, "train", scope)["class"].nunique())
    conditioning = build_conditioning(conditioning_kind, pairs, scope, data, params["classify"], run["seed"],
                                      run["inferred_epochs"], run["inferred_reader"])
    settings = objective_settings(settings, run, objective, direction)
    settings, output_note = output_settings(settings, run, data.targets)
    frames = len(data.targets)
    if settings.get("views", 1) > 1:
        started = time.perf_counter()
        data = with_frame_views(data, pairs, splits, direction, scope, settings["views"], Path(tiles_path),
                                params["roi"], settings["size"], run["seed"])
        print(f"train {direction}/{scope}: class_gan.views {settings['views']}: {len(data.targets) - frames} more "
              f"target crops and {len(data.pool_images)} inputs in all, cut from the training frames in "
              f"{time.perf_counter() - started:.1f} s")
    guide = build_guide(settings, data, params["classify"], run["seed"])
    referee = build_referee(settings, data, validation, params["classify"], run["seed"])
    print(f"train {direction}/{scope}: {len(data.targets)} training pairs ({int(data.aligned.sum())} aligned), "
          f"preset '{run['preset']}' (recipe '{run['recipe']}') at {settings['size']} px, {settings['iterations']} iterations of batch "
          f"{settings['batch_size']}, precision {run['precision']}, conditioning {conditioning.kind}, "
          f"objective {objective} ({objective_reason}){output_note}")
    with atomic_output_dir(out_dir) as tmp:
        live, log = _live_logger(tmp / "dvclive")
        checkpoints = Path(checkpoint_root) / direction / scope
        if run["capacity"]["mode"] == "auto" and validation is not None:
            judge = build_judge(run["capacity"]["class_signal"], data, validation, referee, params["classify"],
                                run["seed"])
            result, settings, capacity = train_capacity_auto(data, validation, settings, run, direction, scope,
                                                             checkpoints, log, progress, conditioning, guide, referee,
                                                             judge)
        else:
            result = train_translator(data, settings, run, direction, scope, checkpoints, on_log=log,
                                      progress=progress, validation=validation, conditioning=conditioning,
                                      guide=guide, referee=referee)
            capacity = {"mode": "fixed", "reason": "as set" if run["capacity"]["mode"] == "fixed" else
                        "capacity auto needs validation pairs and this scope has none; the preset was used"}
        live.end()
        preparation = input_preparation(params["roi"], direction, settings["size"], data.inputs, data.pool_images)
        save_generator(tmp / "generator.pt", result.generator, settings, direction, scope, preparation, conditioning)
        summary = _summary(result, data, validation, settings, run, direction, scope, conditioning)
        summary["capacity"] = capacity
        summary["objective"] = {"name": objective, "reason": objective_reason}
        summary["views"] = {"per_frame": int(settings.get("views", 1)), "target_frames": frames,
                            "targets": len(data.targets), "inputs": len(data.pool_images)}
        if objective == "class_gan":
            summary["selection"] = selection_record(settings, result, validation)
        record, times = split_times(summary, RUN_TIMES)
        (tmp / "train.json").write_text(json.dumps(record, indent=2) + "\n")
        write_timing(tmp, times)
    print(f"train {direction}/{scope}: {result.steps} steps in {result.seconds:.1f} s "
          f"({summary['seconds_per_iteration']:.3f} s/it) -> {out_dir}")
    return summary


def _not_applicable(pairs_dir: Path, direction: str, scope: str, out_dir: Path) -> dict:
    """No pairs at all for ``direction`` (e.g. a one-modality dataset): write train.json with the reason
    and no generator.pt, so the generate stage and the report say why there is no translation."""
    reason = "the pairs stage found no pairs for this direction"
    summary_path = pairs_dir / "summary.json"
    if summary_path.is_file():
        recorded = json.loads(summary_path.read_text()).get("translation")
        if isinstance(recorded, dict) and recorded.get("reason"):
            reason = recorded["reason"]
        elif isinstance(recorded, str) and recorded:
            reason = recorded
    summary = {"direction": direction, "scope": scope, "status": f"not applicable: {reason}"}
    with atomic_output_dir(out_dir) as tmp:
        (tmp / "train.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"train {direction}/{scope}: not applicable: {reason}; no model -> {out_dir}")
    return summary
