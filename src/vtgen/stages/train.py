"""Train stage: one conditional GAN per direction (V2T, T2V) and scope entry.

``train_translator`` is the whole training loop in one function: it draws batches from the
pair table (aligned pairs as they are; unaligned ones get a fresh input from the same class at
every draw, as the authors did), applies the paper's random positioning, alternates a
discriminator and a generator step, logs losses, writes checkpoints atomically and resumes
from them. ``run_train`` is the stage around it: it reads the pair tables, writes the final
generator, ``train.json`` and the dvclive loss log into one output folder atomically.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from tqdm import tqdm

from vtgen.io.params import model_settings
from vtgen.core.gan import adversarial_loss, make_optimizer, random_positioning, to_model_range
from vtgen.io.images import atomic_output_dir
from vtgen.io.tables import read_table
from vtgen.core.models import build_discriminator, conditional_pair, count_parameters, UNetGenerator
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.core.device import resolve_device
from vtgen.io.checkpoints import save_atomic, save_generator

LOSS_NAMES = ("loss_d", "loss_g_gan", "loss_g_l1")
CHECKPOINT_NAME = "last.pt"


class TrainingDiverged(RuntimeError):
    """A loss or weight became NaN or infinite; nothing non-finite was saved."""


@dataclass
class PairData:
    """Training pairs as uint8 tensors N x 3 x S x S, with what is needed to redraw unaligned inputs.

    ``input_pool[c]`` holds indices into ``pool_images`` of every training input tile of class
    ``c``; an unaligned pair draws its input from there at every step.
    """

    inputs: torch.Tensor
    targets: torch.Tensor
    classes: list[str]
    aligned: torch.Tensor
    pool_images: torch.Tensor
    input_pool: dict[str, torch.Tensor] = field(default_factory=dict)

    def fingerprint(self) -> str:
        """SHA-256 of the pixel data and pairing, so a checkpoint is only resumed on the same data."""
        digest = hashlib.sha256()
        for tensor in (self.inputs, self.targets, self.aligned, self.pool_images):
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
    source_mod = DIRECTIONS[direction][0]
    pool = splits[(splits["split"] == split) & (splits["modality"] == source_mod)
                  & splits["class"].isin(set(train["class"]))].sort_values("path")
    pool_classes = pool["class"].to_numpy()
    return PairData(
        inputs=read_tiles(list(train["input_path"]), size, root),
        targets=read_tiles(list(train["target_path"]), size, root),
        classes=list(train["class"]),
        aligned=torch.tensor(train["aligned"].to_numpy(dtype=bool)),
        pool_images=read_tiles(list(pool["path"]), size, root),
        input_pool={c: torch.from_numpy(np.flatnonzero(pool_classes == c)) for c in sorted(set(train["class"]))},
    )


def draw_batch(data: PairData, batch_size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch of (input, target) uint8 images; unaligned targets get a fresh random input of their class."""
    index = torch.randint(0, len(data.targets), (batch_size,), generator=generator)
    inputs = data.inputs[index]  # advanced indexing already copies
    for row, i in enumerate(index.tolist()):
        if not data.aligned[i]:
            pool = data.input_pool[data.classes[i]]
            if len(pool):
                inputs[row] = data.pool_images[pool[torch.randint(0, len(pool), (1,), generator=generator)]][0]
    return inputs, data.targets[index]


@dataclass(frozen=True)
class SpeedChoices:
    """How ``train_translator`` executes a step; precision (fp32 | bf16) stays in params. None of these
    changes the batches drawn or the loss being optimised (tests/test_train.py checks each). The
    defaults are what measured faster on the project's CPU (benchmarks/train_speed.py, 1 thread,
    speed-up of each choice alone over the plain fp32 loop, 64 px / 128 px ngf 32):

    ``fused_optimizer`` (on, 1.15-1.6x): Adam's fused step, one kernel over all parameters instead
    of a Python loop of small ops (RMSprop: its foreach step); equal to the plain step up to rounding.
    ``freeze_discriminator`` (on, 1.14-1.3x): the discriminator's weights need no gradient in the
    generator step (pix2pix does the same; those gradients were discarded at the next ``zero_grad``),
    so its weight-gradient convolutions are skipped; weights stay bitwise equal.
    ``channels_last`` (off): NHWC memory format for networks and batches; 1.05-1.08x alone (within
    noise) and slower than NCHW once combined with bf16 on this CPU; may pay on a GPU.
    ``prefetch`` (off): prepare the next batch (draw, scale, random positioning) on a background
    thread, same order and random draws as the sequential loop; preparing costs 0.1-0.3% of a step
    (0.1 ms at 64 px, 20 ms at 256 px with positioning), so there is nothing to hide, and the
    thread competes with torch's own threads.
    """

    fused_optimizer: bool = True
    freeze_discriminator: bool = True
    channels_last: bool = False
    prefetch: bool = False


def _multi_tensor_optimizer(optimizer: torch.optim.Optimizer, device: torch.device) -> torch.optim.Optimizer:
    """The same optimiser and hyper-parameters, rebuilt with its multi-tensor step (fused Adam, foreach RMSprop)."""
    option = {torch.optim.Adam: "fused", torch.optim.RMSprop: "foreach"}.get(type(optimizer))
    if option is None or (option == "fused" and device.type not in ("cpu", "cuda")):
        return optimizer
    return type(optimizer)(optimizer.param_groups[0]["params"], **{**optimizer.defaults, option: True})


def prepare_batch(data: PairData, batch_size: int, noise: bool, sampler: torch.Generator,
                  device: torch.device = torch.device("cpu")) -> tuple[torch.Tensor, torch.Tensor]:
    """One training batch in [-1, 1] on ``device``: ``draw_batch``, scaling and (with ``noise``) random
    positioning, every random draw from ``sampler``."""
    inputs, targets = draw_batch(data, batch_size, sampler)
    x, y = to_model_range(inputs).to(device), to_model_range(targets).to(device)
    if noise:
        x, y = random_positioning(x, y, sampler)
    return x, y


class BatchStream:
    """Training batches on ``device`` in the order of repeated ``prepare_batch`` calls on ``sampler``,
    optionally prepared up to ``depth`` batches ahead on a background thread (on the CPU, then
    copied to ``device`` by the training thread; pinned when that is a GPU).

    Only the stream touches ``sampler`` once it is created, so the batches are the same with and
    without the thread. ``sampler_state`` is the sampler's state right after the last batch handed
    out: what a checkpoint must store for a resumed run to draw the same next batch.
    """

    def __init__(self, data: PairData, batch_size: int, noise: bool, sampler: torch.Generator,
                 device: torch.device = torch.device("cpu"), background: bool = False, depth: int = 2) -> None:
        self._device = device
        self._make = lambda: prepare_batch(data, batch_size, noise, sampler, torch.device("cpu") if background else device)
        self._sampler = sampler
        self.sampler_state = sampler.get_state()
        self._queue: queue.Queue | None = None
        if background:
            self._queue = queue.Queue(maxsize=depth)
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._produce, name="vtgen-batches", daemon=True)
            self._thread.start()

    def _put(self, item: tuple) -> None:
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _produce(self) -> None:
        try:
            while not self._stop.is_set():
                x, y = self._make()
                if self._device.type == "cuda":
                    x, y = x.pin_memory(), y.pin_memory()
                self._put((x, y, self._sampler.get_state()))
        except BaseException as exc:  # handed to the training thread, raised at its next batch
            self._put((exc,))

    def next(self) -> tuple[torch.Tensor, torch.Tensor]:
        if self._queue is None:
            x, y = self._make()
            self.sampler_state = self._sampler.get_state()
            return x, y
        item = self._queue.get()
        if len(item) == 1:
            raise item[0]
        x, y, self.sampler_state = item
        cuda = self._device.type == "cuda"
        return x.to(self._device, non_blocking=cuda), y.to(self._device, non_blocking=cuda)

    def close(self) -> None:
        if self._queue is not None:
            self._stop.set()
            self._thread.join()


def _non_finite_tensors(*modules: torch.nn.Module) -> list[str]:
    """Names of the floating state tensors (weights, BatchNorm running statistics) holding NaN or inf."""
    return [f"{type(m).__name__}.{name}" for m in modules for name, t in m.state_dict().items()
            if t.is_floating_point() and not bool(torch.isfinite(t).all())]


def _describe(bad: list[str]) -> str:
    return ", ".join(bad[:3]) + (f" and {len(bad) - 3} more" if len(bad) > 3 else "")


def _config_fingerprint(settings: dict, run: dict, direction: str, scope: str, data_hash: str) -> str:
    """What a checkpoint must match to be resumed: everything except the iteration count."""
    keyed = {"settings": {k: v for k, v in settings.items() if k != "iterations"},
             "seed": run["seed"], "precision": run["precision"], "direction": direction, "scope": scope, "data": data_hash}
    return hashlib.sha256(json.dumps(keyed, sort_keys=True).encode()).hexdigest()


@dataclass
class TrainResult:
    generator: UNetGenerator
    history: list[dict]
    steps: int
    seconds: float
    resumed_from: int
    device: str


def validation_l1(generator: UNetGenerator, validation: PairData, batch_size: int = 32) -> float:
    """Mean |G(x) - y| on [-1, 1] over the aligned validation pairs, in eval mode (no dropout, running BN)."""
    device = next(generator.parameters()).device
    keep = validation.aligned.nonzero().flatten()
    was_training = generator.training
    generator.eval()
    total = 0.0
    with torch.no_grad():
        for start in range(0, len(keep), batch_size):
            index = keep[start:start + batch_size]
            x = to_model_range(validation.inputs[index]).to(device)
            y = to_model_range(validation.targets[index]).to(device)
            total += float((generator(x).float() - y).abs().mean(dim=(1, 2, 3)).sum())
    generator.train(was_training)
    return total / len(keep)


def train_translator(data: PairData, settings: dict, run: dict, direction: str, scope: str,
                     checkpoint_dir: Path | None = None, on_log=None, progress: bool = True,
                     validation: PairData | None = None, speed: SpeedChoices | None = None) -> TrainResult:
    """Train one conditional GAN on ``data`` for ``settings['iterations']`` steps.

    ``settings`` is a presets block (size, ngf, ndf, kernel, discriminator, patch_layers,
    gan_loss, l1_weight, optimizer, lr, betas, batch_size, iterations, noise); ``run`` holds
    device, precision, threads, checkpoint_every, resume, log_every and seed. Per step:
    D minimises ½[L(D(x, y), real) + L(D(x, G(x)), fake)]; G minimises
    L(D(x, G(x)), real) + l1_weight·|G(x) − y|₁ (pix2pix, Isola et al. 2017, eq. 4).
    Losses are averaged over each ``log_every`` window and passed to ``on_log(row)``; at each
    checkpoint the row also holds ``val_l1``, the L1 error on the aligned pairs of ``validation``.
    A non-finite loss raises TrainingDiverged naming the step and the last good checkpoint.
    ``speed`` picks how steps are executed (:class:`SpeedChoices`; default: the measured choices);
    it never changes the batches drawn nor, except through floating-point rounding of a fused
    optimiser step, the weights.
    """
    speed = speed or SpeedChoices()
    device = resolve_device(run["device"])
    if device.type == "cpu":
        torch.set_num_threads(run["threads"])
    torch.manual_seed(run["seed"])
    sampler = torch.Generator().manual_seed(run["seed"])
    size, iterations = settings["size"], settings["iterations"]
    generator = UNetGenerator(size, settings["ngf"], settings["kernel"]).to(device)
    discriminator = build_discriminator(settings["discriminator"], size, settings["ndf"], settings["kernel"],
                                        settings["patch_layers"]).to(device)
    memory_format = torch.channels_last if speed.channels_last else torch.contiguous_format
    generator, discriminator = generator.to(memory_format=memory_format), discriminator.to(memory_format=memory_format)
    opt_g = make_optimizer(generator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    opt_d = make_optimizer(discriminator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    if speed.fused_optimizer:  # a resumed checkpoint's own setting wins (load_state_dict restores it)
        opt_g, opt_d = _multi_tensor_optimizer(opt_g, device), _multi_tensor_optimizer(opt_d, device)
    autocast = (torch.autocast(device_type=device.type, dtype=torch.bfloat16) if run["precision"] == "bf16"
                else contextlib.nullcontext())

    fingerprint = _config_fingerprint(settings, run, direction, scope, data.fingerprint())
    checkpoint_path = checkpoint_dir / CHECKPOINT_NAME if checkpoint_dir else None
    step, history, seconds_before, resumed_from, saved_step = 0, [], 0.0, 0, None
    if checkpoint_path and run["resume"] and checkpoint_path.is_file():
        state = torch.load(checkpoint_path, map_location=device, weights_only=False)
        if state["fingerprint"] != fingerprint:
            print(f"train {direction}/{scope}: checkpoint {checkpoint_path} is for another configuration; starting afresh")
        elif state["step"] > iterations:
            print(f"train {direction}/{scope}: checkpoint is at step {state['step']} > iterations {iterations}; starting afresh")
        else:
            generator.load_state_dict(state["generator"])
            discriminator.load_state_dict(state["discriminator"])
            opt_g.load_state_dict(state["opt_g"])
            opt_d.load_state_dict(state["opt_d"])
            sampler.set_state(state["sampler_rng"])
            torch.set_rng_state(state["torch_rng"])
            if device.type == "cuda" and state.get("cuda_rng") is not None:
                torch.cuda.set_rng_state(state["cuda_rng"])
            step, history, seconds_before = state["step"], state["history"], state["seconds"]
            resumed_from = saved_step = step
            print(f"train {direction}/{scope}: resuming from step {step} ({checkpoint_path})")
    if on_log:
        for row in history:
            on_log(row)

    def save_checkpoint(at_step: int, elapsed: float) -> None:
        nonlocal saved_step
        if not checkpoint_path:
            return
        bad = _non_finite_tensors(generator, discriminator)
        if bad:
            raise TrainingDiverged(f"{direction}/{scope}: non-finite weights at step {at_step} ({_describe(bad)}); "
                                   f"checkpoint not written; {last_good()}")
        checkpoint_dir.mkdir(parents=True, exist_ok=True)
        save_atomic({
            "fingerprint": fingerprint, "step": at_step, "history": history, "seconds": elapsed,
            "generator": generator.state_dict(), "discriminator": discriminator.state_dict(),
            "opt_g": opt_g.state_dict(), "opt_d": opt_d.state_dict(),
            "sampler_rng": batches.sampler_state, "torch_rng": torch.get_rng_state(),
            "cuda_rng": torch.cuda.get_rng_state() if device.type == "cuda" else None,
        }, checkpoint_path)
        saved_step = at_step

    def last_good() -> str:
        if saved_step is None:
            return "no checkpoint was written"
        return f"last good checkpoint: {checkpoint_path} (step {saved_step})"

    generator.train()
    discriminator.train()
    window: list[torch.Tensor] = []
    started = time.perf_counter()
    bar = tqdm(total=iterations, initial=step, desc=f"train {direction}/{scope}", unit="it", disable=not progress,
               mininterval=1.0, dynamic_ncols=True)
    batches = BatchStream(data, settings["batch_size"], settings["noise"], sampler, device,
                          background=speed.prefetch and step < iterations)
    try:
        while step < iterations:
            x, y = batches.next()
            if speed.channels_last:
                x, y = x.contiguous(memory_format=memory_format), y.contiguous(memory_format=memory_format)
            with autocast:
                fake = generator(x)
                d_real = discriminator(conditional_pair(x, y))
                d_fake = discriminator(conditional_pair(x, fake.detach()))
            loss_d = 0.5 * (adversarial_loss(d_real, True, settings["gan_loss"])
                            + adversarial_loss(d_fake, False, settings["gan_loss"]))
            opt_d.zero_grad(set_to_none=True)
            loss_d.backward()
            opt_d.step()
            if speed.freeze_discriminator:  # G's step needs gradients through D, not of D's weights
                discriminator.requires_grad_(False)
            with autocast:
                d_fake = discriminator(conditional_pair(x, fake))
            loss_g_gan = adversarial_loss(d_fake, True, settings["gan_loss"])
            loss_g_l1 = F.l1_loss(fake.float(), y)
            loss_g = loss_g_gan + settings["l1_weight"] * loss_g_l1 if settings["l1_weight"] else loss_g_gan
            opt_g.zero_grad(set_to_none=True)
            loss_g.backward()
            opt_g.step()
            if speed.freeze_discriminator:
                discriminator.requires_grad_(True)
            step += 1
            window.append(torch.stack([loss_d.detach(), loss_g_gan.detach(), loss_g_l1.detach()]))

            if step % run["log_every"] == 0 or step == iterations or step % run["checkpoint_every"] == 0:
                losses = torch.stack(window).float().cpu()  # the only host sync: once per logging window
                bad = (~torch.isfinite(losses).all(dim=1)).nonzero()
                if len(bad):
                    first = step - len(window) + int(bad[0]) + 1
                    raise TrainingDiverged(f"{direction}/{scope}: non-finite loss at step {first} "
                                           f"({', '.join(f'{n}={v:.4g}' for n, v in zip(LOSS_NAMES, losses[int(bad[0])].tolist()))}); "
                                           f"nothing after it was saved; {last_good()}")
                elapsed = seconds_before + time.perf_counter() - started
                row = {"step": step, **dict(zip(LOSS_NAMES, losses.mean(dim=0).tolist())),
                       "images_per_s": (step - resumed_from) * settings["batch_size"] / max(elapsed - seconds_before, 1e-9)}
                at_checkpoint = step % run["checkpoint_every"] == 0 or step == iterations
                if at_checkpoint and validation is not None and bool(validation.aligned.any()):
                    row["val_l1"] = validation_l1(generator, validation)
                history.append(row)
                window = []
                if on_log:
                    on_log(row)
                bar.set_postfix({"D": f"{row['loss_d']:.3f}", "G": f"{row['loss_g_gan']:.3f}", "L1": f"{row['loss_g_l1']:.3f}",
                                 "img/s": f"{row['images_per_s']:.0f}"}, refresh=False)
                if at_checkpoint:
                    save_checkpoint(step, elapsed)
            bar.update(1)
    finally:
        batches.close()
        bar.close()
    bad = _non_finite_tensors(generator)
    if bad:
        raise TrainingDiverged(f"{direction}/{scope}: non-finite generator weights at step {step} ({_describe(bad)}); "
                               f"{last_good()}")
    seconds = seconds_before + time.perf_counter() - started
    return TrainResult(generator.cpu().to(memory_format=torch.contiguous_format), history, step, seconds,
                       resumed_from, str(device))


def run_train(params: dict, direction: str, scope: str, pairs_dir: str | Path, out_dir: str | Path,
              checkpoint_root: str | Path = "checkpoints", progress: bool = True) -> dict:
    """Stage entry: train ``direction`` for one ``scope`` entry and write ``out_dir`` atomically.

    ``out_dir`` receives generator.pt, train.json and dvclive/ (per-step losses). Checkpoints
    live outside it, in ``checkpoint_root/<direction>/<scope>/``, because Snakemake and DVC
    delete a stage's outputs before rerunning it and a resume must survive that.
    """
    from dvclive import Live
    from scmrepo.exceptions import SCMError

    if direction not in DIRECTIONS:
        raise ValueError(f"unknown direction '{direction}' (allowed: {', '.join(DIRECTIONS)})")
    if scope not in params["translation"]["scope"]:
        raise ValueError(f"scope '{scope}' is not listed in translation.scope {params['translation']['scope']}")
    settings, run = model_settings(params), params["translation"]
    pairs_dir = Path(pairs_dir)
    pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    data = load_pair_data(pairs, splits, direction, scope, settings["size"])
    validation = (load_pair_data(pairs, splits, direction, scope, settings["size"], split="val")
                  if not pairs_in(pairs, "val", scope).empty else None)
    tile_side = int(data.targets.shape[-1])
    print(f"train {direction}/{scope}: {len(data.targets)} training pairs ({int(data.aligned.sum())} aligned), "
          f"preset '{run['preset']}' at {settings['size']} px, {settings['iterations']} iterations of batch "
          f"{settings['batch_size']}, {run['precision']}")
    with atomic_output_dir(out_dir) as tmp:
        try:
            live = Live(dir=str(tmp / "dvclive"), save_dvc_exp=False, dvcyaml=None, report=None)
        except SCMError as exc:  # dvclive reads the Git revision of the DVC project it runs in
            raise RuntimeError(f"dvclive cannot log in this Git repository ({exc}); "
                               f"make a first commit (`git commit`) and run again") from exc

        def log(row: dict) -> None:
            live.step = row["step"]
            for name in (*LOSS_NAMES, "images_per_s"):
                live.log_metric(f"train/{name}", row[name])
            if "val_l1" in row:
                live.log_metric("val/l1", row["val_l1"])

        result = train_translator(data, settings, run, direction, scope,
                                  Path(checkpoint_root) / direction / scope, on_log=log, progress=progress,
                                  validation=validation)
        live.end()
        save_generator(tmp / "generator.pt", result.generator, settings, direction, scope)
        final = result.history[-1] if result.history else {}
        summary = {
            "direction": direction, "scope": scope, "preset": run["preset"], "settings": settings,
            "precision": run["precision"], "device": result.device, "threads": run["threads"], "seed": run["seed"],
            "training_pairs": len(data.targets), "aligned_pairs": int(data.aligned.sum()), "tile_size": tile_side,
            "generator_parameters": count_parameters(result.generator), "steps": result.steps,
            "resumed_from_step": result.resumed_from, "wall_seconds": round(result.seconds, 2),
            "seconds_per_iteration": round(result.seconds / max(result.steps, 1), 5),
            "final_losses": {k: final.get(k) for k in LOSS_NAMES},
            "validation_pairs": 0 if validation is None else int(validation.aligned.sum()),
            "final_val_l1": final.get("val_l1"),
        }
        (tmp / "train.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"train {direction}/{scope}: {result.steps} steps in {result.seconds:.1f} s "
          f"({summary['seconds_per_iteration']:.3f} s/it) -> {out_dir}")
    return summary
