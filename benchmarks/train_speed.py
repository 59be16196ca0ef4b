"""Seconds per training iteration: a plain pix2pix-style reference loop against vtgen's ``train_translator``.

The **reference** is built here, the plain way: the same networks (``UNetGenerator`` and
``build_discriminator`` with the setting's widths, kernel and batch), eager fp32, contiguous NCHW,
the default optimiser step, and a loop that decodes each batch's PNG tiles from disk on the
training thread (tiles written once to a temporary folder), applies the same random positioning
when the setting has ``noise``, runs the same D and G steps as vtgen and calls ``.item()`` on the
three losses every step.

**vtgen** is ``train_translator`` on the same tiles, decoded once into memory (``read_tiles``),
with one host sync per logging window, the fused Adam / foreach RMSprop step and the discriminator
frozen during the generator step (what :class:`vtgen.core.translator.TranslatorTraining` always
does), timed with ``translation.precision`` fp32 ("combined, fp32") and bf16 ("combined").
Variants are interleaved within each repeat, so machine load hits them alike; the table gives the
median seconds per iteration over the repeats and the median of the per-repeat speed-ups against
the reference timed in the same repeat. Every timing skips ``--warmup`` iterations (allocation,
first-call set-up).

On a machine shared with other jobs, time with ``--threads 1``: with more OpenMP threads than free
cores every variant slows down by large, erratic factors and the ratios mean nothing.

    python benchmarks/train_speed.py                                  # fast, mid32, mid64, paper
    python benchmarks/train_speed.py --settings fast --iterations 24 --repeats 5
    python benchmarks/train_speed.py --settings paper --paper-iterations 2 --repeats 2 --variants reference combined
"""

from __future__ import annotations

import argparse
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from vtgen.io.params import load_params
from vtgen.core.gan import adversarial_loss, make_optimizer, random_positioning
from vtgen.core.models import build_discriminator, conditional_pair, count_parameters, UNetGenerator
from vtgen.stages.train import PairData, prepare_batch, train_translator
from vtgen.io.images import read_tiles

# name -> precision of train_translator; "reference" is the plain loop of this file
VARIANTS = {"combined, fp32": "fp32", "combined": "bf16"}
SHORT = {"reference": "reference", "combined-fp32": "combined, fp32", "combined": "combined"}


def settings_for(params: dict, name: str) -> dict:
    """A preset of params.yaml, or an intermediate setting: mid32 / mid64 = the fast preset at 128 px
    with ngf = ndf = 32 / 64."""
    if name in params["presets"]:
        return dict(params["presets"][name])
    if name in ("mid32", "mid64"):
        width = int(name[3:])
        return dict(params["presets"]["fast"], size=128, ngf=width, ndf=width)
    raise SystemExit(f"unknown setting {name!r} (presets: {', '.join(params['presets'])}, mid32, mid64)")


def write_tiles(folder: Path, size: int, n: int, seed: int = 0) -> tuple[list[str], list[str]]:
    """``n`` input and ``n`` target RGB PNG tiles of side ``size``: smooth random texture plus grain,
    so that they compress and decode like camera tiles rather than like pure noise."""
    rng = np.random.default_rng(seed)
    paths = {"input": [], "target": []}
    for kind in paths:
        for i in range(n):
            coarse = Image.fromarray(rng.integers(0, 256, (size // 8, size // 8, 3), dtype=np.uint8))
            image = np.asarray(coarse.resize((size, size), Image.BICUBIC), dtype=np.int16)
            image = np.clip(image + rng.integers(-12, 13, image.shape), 0, 255).astype(np.uint8)
            path = folder / f"{kind}_{i:03d}.png"
            Image.fromarray(image).save(path)
            paths[kind].append(str(path))
    return paths["input"], paths["target"]


def load_png_batch(paths: list[str]) -> torch.Tensor:
    """Decode PNG files into a float N x 3 x S x S batch in [-1, 1] (what a plain data loader does per step)."""
    arrays = [np.asarray(Image.open(path).convert("RGB")) for path in paths]
    return torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).float() / 127.5 - 1.0


def reference_seconds(settings: dict, inputs: list[str], targets: list[str], warmup: int, iterations: int,
                      seed: int = 0) -> float:
    """Seconds per iteration of the plain loop (see the module docstring)."""
    torch.manual_seed(seed)
    sampler = torch.Generator().manual_seed(seed)
    size = settings["size"]
    generator = UNetGenerator(size, settings["ngf"], settings["kernel"])
    discriminator = build_discriminator(settings["discriminator"], size, settings["ndf"], settings["kernel"],
                                        settings["patch_layers"])
    opt_g = make_optimizer(generator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    opt_d = make_optimizer(discriminator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    generator.train()
    discriminator.train()
    log = []
    for step in range(warmup + iterations):
        if step == warmup:
            started = time.perf_counter()
        index = torch.randint(0, len(inputs), (settings["batch_size"],), generator=sampler).tolist()
        x, y = load_png_batch([inputs[i] for i in index]), load_png_batch([targets[i] for i in index])
        if settings["noise"]:
            x, y = random_positioning(x, y, sampler)
        fake = generator(x)
        loss_d = 0.5 * (adversarial_loss(discriminator(conditional_pair(x, y)), True, settings["gan_loss"])
                        + adversarial_loss(discriminator(conditional_pair(x, fake.detach())), False,
                                           settings["gan_loss"]))
        opt_d.zero_grad()
        loss_d.backward()
        opt_d.step()
        loss_g_gan = adversarial_loss(discriminator(conditional_pair(x, fake)), True, settings["gan_loss"])
        loss_g_l1 = F.l1_loss(fake, y)
        loss_g = loss_g_gan + settings["l1_weight"] * loss_g_l1
        opt_g.zero_grad()
        loss_g.backward()
        opt_g.step()
        log.append((loss_d.item(), loss_g_gan.item(), loss_g_l1.item()))
    return (time.perf_counter() - started) / iterations


def vtgen_seconds(settings: dict, data: PairData, run: dict, precision: str, warmup: int, iterations: int) -> float:
    """Seconds per iteration of ``train_translator``, from the log rows at step ``warmup`` and at the end
    (``iterations`` is a multiple of ``warmup``, which is the logging interval)."""
    stamps = {}
    train_translator(data, dict(settings, iterations=warmup + iterations),
                     dict(run, precision=precision, log_every=warmup), "v2t", "all", progress=False,
                     on_log=lambda row: stamps.__setitem__(row["step"], time.perf_counter()))
    return (stamps[warmup + iterations] - stamps[warmup]) / iterations


def preparation_ms(settings: dict, data: PairData, repeats: int = 20) -> float:
    """Median milliseconds of one ``prepare_batch`` (draw, scale, random positioning) on the training thread."""
    sampler = torch.Generator().manual_seed(0)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        prepare_batch(data, settings["batch_size"], settings["noise"], sampler)
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def benchmark(name: str, settings: dict, run: dict, variants: list[str], warmup: int, iterations: int,
              repeats: int, tiles: int) -> None:
    iterations = -(-iterations // warmup) * warmup  # a multiple of the logging interval
    with tempfile.TemporaryDirectory() as tmp:
        inputs, targets = write_tiles(Path(tmp), settings["size"], tiles)
        images_in, images_out = read_tiles(inputs, settings["size"], Path("/")), read_tiles(targets, settings["size"], Path("/"))
        data = PairData(images_in, images_out, ["c"] * tiles, torch.ones(tiles, dtype=torch.bool), images_in,
                        {"c": torch.arange(tiles)})
        seconds: dict[str, list[float]] = {v: [] for v in variants}
        for _ in range(repeats):
            for variant in variants:
                if variant == "reference":
                    torch.set_num_threads(run["threads"])
                    seconds[variant].append(reference_seconds(settings, inputs, targets, warmup, iterations))
                else:
                    precision = VARIANTS[SHORT[variant]]
                    seconds[variant].append(vtgen_seconds(settings, data, run, precision, warmup, iterations))
        prep = preparation_ms(settings, data)
    g = count_parameters(UNetGenerator(settings["size"], settings["ngf"], settings["kernel"]))
    d = count_parameters(build_discriminator(settings["discriminator"], settings["size"], settings["ndf"],
                                             settings["kernel"], settings["patch_layers"]))
    print(f"\n### {name}: {settings['size']} px, ngf/ndf {settings['ngf']}/{settings['ndf']}, "
          f"{settings['discriminator']} D, kernel {settings['kernel']}, batch {settings['batch_size']}, "
          f"{settings['optimizer']}, noise {settings['noise']}; G {g / 1e6:.1f} M, D {d / 1e6:.1f} M parameters\n")
    print("| variant | precision | s/iteration (median) | speed-up vs reference (median, min-max) | iterations timed | repeats |")
    print("|---|---|---|---|---|---|")
    reference = seconds.get("reference")
    for variant in variants:
        times = seconds[variant]
        if reference:
            ratios = [r / t for r, t in zip(reference, times)]
            speedup = f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})"
        else:
            speedup = "-"
        precision = "fp32" if variant == "reference" else VARIANTS[SHORT[variant]]
        print(f"| {SHORT[variant]} | {precision} | {statistics.median(times):.4f} | {speedup} | {iterations} | {repeats} |",
              flush=True)
    shown = "combined" if "combined" in seconds else variants[-1]
    step = statistics.median(seconds[shown])
    print(f"\nbatch preparation on the training thread (draw, scale, positioning): {prep:.2f} ms per iteration, "
          f"{100 * prep / 1e3 / step:.1f}% of a '{SHORT[shown]}' step", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--settings", nargs="*", default=["fast", "mid32", "mid64", "paper"],
                        help="presets of params.yaml, or mid32 / mid64 (the fast preset at 128 px, ngf/ndf 32 / 64)")
    parser.add_argument("--variants", nargs="*", default=list(SHORT), choices=list(SHORT),
                        help="what to time (reference = the plain loop; the rest are train_translator)")
    parser.add_argument("--threads", type=int, help="torch CPU threads for every variant (default: translation.threads)")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=12, help="timed iterations (rounded up to a multiple of --warmup)")
    parser.add_argument("--paper-warmup", type=int, default=1)
    parser.add_argument("--paper-iterations", type=int, default=2, help="timed iterations of 256 px settings")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tiles", type=int, default=16, help="PNG tiles per side written for the reference loop")
    args = parser.parse_args()
    params = load_params(args.params)
    run = dict(params["translation"], device="cpu", checkpoint_every=10**9, resume=False, seed=0)
    if args.threads:
        run["threads"] = args.threads
    print(f"device: {platform.processor() or 'CPU'}, {run['threads']} torch threads for reference and vtgen alike "
          f"(translation.threads); torch {torch.__version__}; median over {args.repeats} interleaved repeats")
    for name in args.settings:
        settings = settings_for(params, name)
        big = settings["size"] >= 256
        benchmark(name, settings, run, args.variants, args.paper_warmup if big else args.warmup,
                  args.paper_iterations if big else args.iterations, args.repeats, args.tiles)


if __name__ == "__main__":
    main()
