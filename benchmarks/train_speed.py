"""Training-step speed: GFLOP per step, s/it, achieved GFLOP/s and its fraction of the measured matmul peak,
for vtgen's ``TranslatorTraining.step`` against pix2pix's own training loop and the plain reference loop.

Four methods, each on the same preset (size, ngf/ndf, batch) and the same torch threads:

* **pix2pix loop** - pix2pix's training iteration re-typed here from the design of Isola et al.'s
  pytorch-CycleGAN-and-pix2pix (not imported, not copied): a recursive U-Net of skip blocks
  (``log2(size)`` stride-2 levels, kernel 4, BatchNorm, convs without bias next to BatchNorm, dropout
  0.5 in the ``log2(size) - 5`` 8*ngf blocks next to the innermost one), the n-layer PatchGAN
  (n_layers = the preset's ``patch_layers``), the vanilla GAN loss (BCE with logits against a label
  tensor), plain Adam (lr 2e-4, betas 0.5 / 0.999, the default per-parameter step) and
  ``optimize_parameters``: forward, D step on ``fake.detach()`` and the real pair, D frozen with
  ``requires_grad = False``, G step on GAN + lambda_L1 * L1 (lambda 100). Batches come from memory
  (pix2pix loads them in data-loader worker processes, off the training thread) and no loss is
  read on the host (pix2pix reads them every ``print_freq`` iterations).
* **reference** - the plain loop this benchmark has always timed: vtgen's own networks, eager fp32,
  the default optimiser step, each batch's PNG tiles decoded on the training thread, D's weight
  gradients computed in the G step, ``.item()`` on the three losses every step.
* **vtgen fp32 / bf16** - ``vtgen.core.translator.TranslatorTraining.step`` on in-memory batches
  (fused Adam / foreach RMSprop, D frozen in the G step), ``precision`` fp32 or bf16 (autocast).

FLOP: ``torch.utils.flop_counter.FlopCounterMode`` around one real step of each method (convolutions,
transposed convolutions, matmuls and their backward passes; element-wise work - BatchNorm,
activations, losses, the optimiser - is not counted). Peak: a ``--matmul-size`` square ``torch.mm``
in fp32 and bf16 on the same threads, GFLOP/s = 2 n^3 / t, median of ``--matmul-repeats``.
Timing: each round builds every method afresh, runs ``--warmup`` untimed steps, then times
``--iterations`` steps one by one; the round's figure is the median step. Methods are interleaved
within a round (order rotated per round) so machine load hits them alike; the tables give the median
over rounds of the per-round medians and the median (min-max) of the per-round speed-ups.

bf16 is only fast on CPUs with AVX512-BF16 or AMX; elsewhere oneDNN emulates it and it is slower
than fp32 (the header line says which the CPU has).

    python benchmarks/train_speed.py                               # fast preset, fp32 and bf16, 2 threads
    python benchmarks/train_speed.py --threads 1 --repeats 7
    python benchmarks/train_speed.py --presets fast paper --paper-iterations 2 --paper-warmup 1 --repeats 2
    python benchmarks/train_speed.py --methods pix2pix vtgen --precisions fp32 --profile
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from vtgen.core.gan import adversarial_loss, make_optimizer, random_positioning
from vtgen.core.models import build_discriminator, conditional_pair, count_parameters, init_weights, UNetGenerator  # pix2pix uses the same init
from vtgen.core.translator import TranslatorTraining
from vtgen.io.params import load_params

METHODS = ("pix2pix", "reference", "vtgen")
PRECISIONS = ("fp32", "bf16")
Step = Callable[[], None]


# --------------------------------------------------------------------------------------------------
# pix2pix, re-typed: networks, loss and optimize_parameters
# --------------------------------------------------------------------------------------------------

class SkipBlock(nn.Module):
    """One U-Net level: ``outer`` channels in, a stride-2 down conv to ``inner``, the ``child`` block, a
    stride-2 transposed conv back to ``outer``; inner levels return ``cat(input, result)``. The
    activation of each conv comes first in the next part (pre-activation), as in pix2pix."""

    def __init__(self, outer: int, inner: int, child: nn.Module | None = None, source: int | None = None,
                 outermost: bool = False, dropout: bool = False) -> None:
        super().__init__()
        self.outermost = outermost
        source = outer if source is None else source
        down = nn.Conv2d(source, inner, 4, 2, 1, bias=False)  # BatchNorm model: no bias beside BatchNorm
        up_in = inner if child is None else 2 * inner  # the child returns its input and its output stacked
        if outermost:
            parts = [down, child, nn.ReLU(True), nn.ConvTranspose2d(up_in, outer, 4, 2, 1), nn.Tanh()]
        elif child is None:  # innermost: no BatchNorm after its down conv
            parts = [nn.LeakyReLU(0.2, True), down, nn.ReLU(True),
                     nn.ConvTranspose2d(up_in, outer, 4, 2, 1, bias=False), nn.BatchNorm2d(outer)]
        else:
            parts = [nn.LeakyReLU(0.2, True), down, nn.BatchNorm2d(inner), child, nn.ReLU(True),
                     nn.ConvTranspose2d(up_in, outer, 4, 2, 1, bias=False), nn.BatchNorm2d(outer)]
            if dropout:
                parts.append(nn.Dropout(0.5))
        self.body = nn.Sequential(*parts)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x) if self.outermost else torch.cat([x, self.body(x)], 1)


class Pix2PixUNet(nn.Module):
    """pix2pix's U-Net generator with ``downs`` levels (1x1 bottleneck for a ``2**downs`` image)."""

    def __init__(self, in_channels: int, out_channels: int, downs: int, ngf: int) -> None:
        super().__init__()
        if downs < 5:
            raise ValueError("pix2pix's U-Net needs at least 5 levels (32 px)")
        block = SkipBlock(8 * ngf, 8 * ngf)
        for _ in range(downs - 5):
            block = SkipBlock(8 * ngf, 8 * ngf, block, dropout=True)
        for width in (4 * ngf, 2 * ngf, ngf):
            block = SkipBlock(width, 2 * width, block)
        self.net = SkipBlock(out_channels, ngf, block, source=in_channels, outermost=True)
        self.apply(init_weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class Pix2PixPatchGAN(nn.Module):
    """pix2pix's n-layer PatchGAN: kernel 4, padding 1, ``layers`` stride-2 convs then two stride-1 convs."""

    def __init__(self, in_channels: int, ndf: int, layers: int = 3) -> None:
        super().__init__()
        parts: list[nn.Module] = [nn.Conv2d(in_channels, ndf, 4, 2, 1), nn.LeakyReLU(0.2, True)]
        width = ndf
        for n in range(1, layers + 1):
            target = ndf * min(2 ** n, 8)
            stride = 2 if n < layers else 1
            parts += [nn.Conv2d(width, target, 4, stride, 1, bias=False), nn.BatchNorm2d(target),
                      nn.LeakyReLU(0.2, True)]
            width = target
        parts.append(nn.Conv2d(width, 1, 4, 1, 1))
        self.net = nn.Sequential(*parts)
        self.apply(init_weights)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class VanillaGANLoss(nn.Module):
    """BCE with logits against a tensor of the real (1) or fake (0) label shaped like the prediction."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("real", torch.tensor(1.0))
        self.register_buffer("fake", torch.tensor(0.0))
        self.bce = nn.BCEWithLogitsLoss()

    def forward(self, prediction: torch.Tensor, is_real: bool) -> torch.Tensor:
        return self.bce(prediction, (self.real if is_real else self.fake).expand_as(prediction))


class Pix2PixModel:
    """pix2pix's training model: networks, Adam optimisers and ``optimize_parameters``."""

    def __init__(self, size: int, ngf: int, ndf: int, layers: int, lambda_l1: float = 100.0) -> None:
        self.G = Pix2PixUNet(3, 3, size.bit_length() - 1, ngf).train()
        self.D = Pix2PixPatchGAN(6, ndf, layers).train()
        self.gan_loss, self.lambda_l1 = VanillaGANLoss(), lambda_l1
        self.opt_G = torch.optim.Adam(self.G.parameters(), lr=2e-4, betas=(0.5, 0.999))
        self.opt_D = torch.optim.Adam(self.D.parameters(), lr=2e-4, betas=(0.5, 0.999))

    @staticmethod
    def set_requires_grad(net: nn.Module, flag: bool) -> None:
        for p in net.parameters():
            p.requires_grad = flag

    def optimize_parameters(self, real_a: torch.Tensor, real_b: torch.Tensor) -> None:
        fake_b = self.G(real_a)
        # D: fake pair (detached from G) and real pair, halved
        self.set_requires_grad(self.D, True)
        self.opt_D.zero_grad()
        fake_pair = torch.cat((real_a, fake_b), 1)
        loss_d = 0.5 * (self.gan_loss(self.D(fake_pair.detach()), False)
                        + self.gan_loss(self.D(torch.cat((real_a, real_b), 1)), True))
        loss_d.backward()
        self.opt_D.step()
        # G: fool D (frozen) and stay close to the target
        self.set_requires_grad(self.D, False)
        self.opt_G.zero_grad()
        loss_g = self.gan_loss(self.D(fake_pair), True) + self.lambda_l1 * F.l1_loss(fake_b, real_b)
        loss_g.backward()
        self.opt_G.step()


# --------------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------------

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


class Tiles:
    """The same tiles as PNG files (for the reference loop) and decoded in memory (for the others)."""

    def __init__(self, folder: Path, size: int, n: int) -> None:
        self.inputs, self.targets = write_tiles(folder, size, n)
        self.x, self.y = load_png_batch(self.inputs), load_png_batch(self.targets)

    def memory_batch(self, sampler: torch.Generator, batch: int, noise: bool) -> tuple[torch.Tensor, torch.Tensor]:
        index = torch.randint(0, len(self.inputs), (batch,), generator=sampler)
        x, y = self.x[index], self.y[index]
        return random_positioning(x, y, sampler) if noise else (x, y)


# --------------------------------------------------------------------------------------------------
# the methods: each returns one training step as a closure over fresh networks
# --------------------------------------------------------------------------------------------------

def pix2pix_step(settings: dict, tiles: Tiles, seed: int = 0) -> Step:
    torch.manual_seed(seed)
    sampler = torch.Generator().manual_seed(seed)
    model = Pix2PixModel(settings["size"], settings["ngf"], settings["ndf"], settings["patch_layers"])

    def step() -> None:
        model.optimize_parameters(*tiles.memory_batch(sampler, settings["batch_size"], False))
    step.model = model  # type: ignore[attr-defined]
    return step


def reference_step(settings: dict, tiles: Tiles, seed: int = 0) -> Step:
    """The plain loop (see the module docstring), one iteration per call."""
    torch.manual_seed(seed)
    sampler = torch.Generator().manual_seed(seed)
    size = settings["size"]
    generator = UNetGenerator(size, settings["ngf"], settings["kernel"]).train()
    discriminator = build_discriminator(settings["discriminator"], size, settings["ndf"], settings["kernel"],
                                        settings["patch_layers"]).train()
    opt_g = make_optimizer(generator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    opt_d = make_optimizer(discriminator.parameters(), settings["optimizer"], settings["lr"], settings["betas"])
    log = []

    def step() -> None:
        index = torch.randint(0, len(tiles.inputs), (settings["batch_size"],), generator=sampler).tolist()
        x = load_png_batch([tiles.inputs[i] for i in index])
        y = load_png_batch([tiles.targets[i] for i in index])
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
    return step


def vtgen_step(settings: dict, tiles: Tiles, precision: str, seed: int = 0) -> Step:
    torch.manual_seed(seed)
    sampler = torch.Generator().manual_seed(seed)
    training = TranslatorTraining(settings, "cpu", precision)

    def step() -> None:
        training.step(*tiles.memory_batch(sampler, settings["batch_size"], settings["noise"]))
    step.training = training  # type: ignore[attr-defined]
    return step


def build(method: str, settings: dict, tiles: Tiles) -> Step:
    """``method`` is "pix2pix", "reference", "vtgen fp32" or "vtgen bf16"."""
    if method == "pix2pix":
        return pix2pix_step(settings, tiles)
    if method == "reference":
        return reference_step(settings, tiles)
    return vtgen_step(settings, tiles, method.split()[1])


def precision_of(method: str) -> str:
    return method.split()[1] if method.startswith("vtgen") else "fp32"


# --------------------------------------------------------------------------------------------------
# measurements
# --------------------------------------------------------------------------------------------------

def step_flops(method: str, settings: dict, tiles: Tiles) -> int:
    """FLOP of one step (after one warm-up step, so lazily created optimiser state is not in it)."""
    step = build(method, settings, tiles)
    step()
    with FlopCounterMode(display=False) as counter:
        step()
    return counter.get_total_flops()


def matmul_peak(n: int, dtype: torch.dtype, repeats: int) -> float:
    """GFLOP/s of an n x n by n x n ``torch.mm`` (median of ``repeats`` after one warm-up)."""
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    out = torch.empty(n, n, dtype=dtype)
    torch.mm(a, b, out=out)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        torch.mm(a, b, out=out)
        times.append(time.perf_counter() - start)
    return 2 * n ** 3 / statistics.median(times) / 1e9


def time_round(step: Step, warmup: int, iterations: int) -> float:
    """Median seconds of one step over ``iterations`` timed steps after ``warmup`` untimed ones."""
    for _ in range(warmup):
        step()
    times = []
    for _ in range(iterations):
        start = time.perf_counter()
        step()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def profile_table(method: str, settings: dict, tiles: Tiles, steps: int = 5, rows: int = 12) -> str:
    """torch.profiler's top operators by self CPU time over ``steps`` steps (after 2 warm-up steps)."""
    step = build(method, settings, tiles)
    step()
    step()
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        for _ in range(steps):
            step()
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


# --------------------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------------------

def cpu_description() -> tuple[str, set[str]]:
    model, flags = platform.processor() or "CPU", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("CPU", platform.processor()):
                model = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    return model, flags


def load_average() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def settings_for(params: dict, name: str) -> dict:
    """A preset of params.yaml, or mid32 / mid64 = the fast preset at 128 px with ngf = ndf = 32 / 64."""
    if name in params["presets"]:
        return dict(params["presets"][name])
    if name in ("mid32", "mid64"):
        width = int(name[3:])
        return dict(params["presets"]["fast"], size=128, ngf=width, ndf=width)
    raise SystemExit(f"unknown preset {name!r} (presets: {', '.join(params['presets'])}, mid32, mid64)")


def ratio_text(numerators: list[float], denominators: list[float]) -> str:
    ratios = [a / b for a, b in zip(numerators, denominators)]
    return f"{statistics.median(ratios):.2f}x ({min(ratios):.2f}-{max(ratios):.2f})"


def benchmark(name: str, settings: dict, methods: list[str], peaks: dict[str, float],
              counts: dict[str, tuple[int, int]], repeats: int, tiles_n: int, profile: bool) -> None:
    """``counts``: (warm-up, timed) steps per method and round."""
    with tempfile.TemporaryDirectory() as tmp:
        tiles = Tiles(Path(tmp), settings["size"], tiles_n)
        flops = {m: step_flops(m, settings, tiles) for m in methods}
        seconds: dict[str, list[float]] = {m: [] for m in methods}
        for round_ in range(repeats):
            order = methods[round_ % len(methods):] + methods[:round_ % len(methods)]
            for method in order:
                seconds[method].append(time_round(build(method, settings, tiles), *counts[method]))
        profiles = {m: profile_table(m, settings, tiles) for m in methods if profile and m != "reference"}

    g = count_parameters(UNetGenerator(settings["size"], settings["ngf"], settings["kernel"]))
    d = count_parameters(build_discriminator(settings["discriminator"], settings["size"], settings["ndf"],
                                             settings["kernel"], settings["patch_layers"]))
    p2p = Pix2PixModel(settings["size"], settings["ngf"], settings["ndf"], settings["patch_layers"])
    print(f"\n### {name}: {settings['size']} px, ngf/ndf {settings['ngf']}/{settings['ndf']}, "
          f"{settings['discriminator']} D, kernel {settings['kernel']}, batch {settings['batch_size']}, "
          f"{settings['optimizer']}, noise {settings['noise']}; vtgen G {g / 1e6:.2f} M, D {d / 1e6:.2f} M "
          f"parameters; pix2pix G {count_parameters(p2p.G) / 1e6:.2f} M, D {count_parameters(p2p.D) / 1e6:.2f} M "
          f"(kernel 4, PatchGAN with {settings['patch_layers']} layers, Adam)")
    if settings["kernel"] != 4 or settings["discriminator"] != "patch" or settings["optimizer"] != "adam":
        print("\n(pix2pix keeps its own kernel 4, PatchGAN and Adam: it is not the same architecture as this preset)")
    shown = {}
    for method in methods:
        shown.setdefault(counts[method], []).append(method)
    print("\n" + "; ".join(f"{', '.join(ms)}: {n} timed steps after {w} warm-up steps" for (w, n), ms in shown.items())
          + f" per round; {repeats} interleaved rounds; s/it = median over rounds of the round's median step\n")
    print("| method | precision | GFLOP/step | s/it (median) | s/it (min-max over rounds) | achieved GFLOP/s "
          "| matmul peak GFLOP/s | fraction of peak |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for method in methods:
        t, precision = seconds[method], precision_of(method)
        rate = flops[method] / statistics.median(t) / 1e9
        print(f"| {method.split()[0]} | {precision} | {flops[method] / 1e9:.2f} | {statistics.median(t):.4f} | "
              f"{min(t):.4f}-{max(t):.4f} | {rate:.1f} | {peaks[precision]:.1f} | {100 * rate / peaks[precision]:.0f}% |")
    if "vtgen bf16" in methods and "fp32" in peaks and peaks["bf16"] < peaks["fp32"] / 4:
        rate = flops["vtgen bf16"] / statistics.median(seconds["vtgen bf16"]) / 1e9
        print(f"\n(bf16 is emulated here: the bf16 torch.mm is no hardware peak - the convolutions can beat it; "
              f"against the fp32 peak, vtgen bf16 reaches {100 * rate / peaks['fp32']:.1f}%)")
    baselines = [b for b in ("pix2pix", "reference") if b in methods]
    if baselines:
        print("\nSpeed-up = baseline s/it / method s/it, median (min-max) of the per-round ratios\n")
        print("| method | precision | " + " | ".join(f"vs {b} loop" if b == "pix2pix" else f"vs {b}"
                                                   for b in baselines) + " |")
        print("|---|---|" + "---:|" * len(baselines))
        for method in methods:
            cells = [ratio_text(seconds[b], seconds[method]) for b in baselines]
            print(f"| {method.split()[0]} | {precision_of(method)} | " + " | ".join(cells) + " |")
    for method, table in profiles.items():
        print(f"\n{method}: top operators by self CPU time, 5 steps\n\n```\n{table}```")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--presets", nargs="+", default=["fast"],
                        help="presets of params.yaml (fast, paper, ...) or mid32 / mid64 (fast at 128 px, width 32 / 64)")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--precisions", nargs="+", default=list(PRECISIONS), choices=PRECISIONS,
                        help="vtgen's precisions (pix2pix and the reference are fp32)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads for every method and the matmul")
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=10, help="timed steps per method and round")
    parser.add_argument("--paper-warmup", type=int, default=1, help="warm-up steps at 256 px and more")
    parser.add_argument("--paper-iterations", type=int, default=2, help="timed steps at 256 px and more")
    parser.add_argument("--bf16-warmup", type=int, help="warm-up steps of vtgen bf16 (default: --warmup on a CPU "
                        "with AVX512-BF16 or AMX, else 1: emulated bf16 runs at about 1 GFLOP/s)")
    parser.add_argument("--bf16-iterations", type=int,
                        help="timed steps of vtgen bf16 (default: --iterations with native bf16, else 2)")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved rounds")
    parser.add_argument("--tiles", type=int, default=16, help="tiles per side (PNG files for the reference loop)")
    parser.add_argument("--matmul-size", type=int, default=2048, help="n of the fp32 peak matmul")
    parser.add_argument("--bf16-matmul-size", type=int,
                        help="n of the bf16 peak matmul (default: --matmul-size with native bf16, else 512: an "
                             "emulated 2048 bf16 matmul takes minutes)")
    parser.add_argument("--matmul-repeats", type=int, default=5)
    parser.add_argument("--profile", action="store_true", help="also print torch.profiler's top operators per method")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    params = load_params(args.params)
    model, flags = cpu_description()
    native = [f for f in ("avx512_bf16", "amx_bf16") if f in flags]
    print(f"date {datetime.date.today()}; CPU: {model}, {os.cpu_count()} logical CPUs; "
          f"AVX512-BF16 {'yes' if 'avx512_bf16' in flags else 'no'}, AMX-BF16 {'yes' if 'amx_bf16' in flags else 'no'}, "
          f"AVX2 {'yes' if 'avx2' in flags else 'no'}, AVX-512F {'yes' if 'avx512f' in flags else 'no'}; "
          f"torch {torch.__version__} (CPU capability {torch.backends.cpu.get_cpu_capability()}), "
          f"{torch.get_num_threads()} torch threads")
    if not native and "bf16" in args.precisions:
        print("no native bf16 on this CPU: bf16 matmuls and convolutions are emulated (expect bf16 slower than fp32)")
    print(f"load average before: {load_average()}")

    methods = [m for m in args.methods if m != "vtgen"]
    if "vtgen" in args.methods:
        methods += [f"vtgen {p}" for p in args.precisions]
    used = {precision_of(m) for m in methods}
    sizes = {"fp32": args.matmul_size,
             "bf16": args.bf16_matmul_size or (args.matmul_size if native else min(args.matmul_size, 512))}
    peaks = {p: matmul_peak(sizes[p], torch.float32 if p == "fp32" else torch.bfloat16, args.matmul_repeats)
             for p in PRECISIONS if p in used}
    print(f"\n| matmul (torch.mm, n x n by n x n) | n | GFLOP/s (median of {args.matmul_repeats}) |\n|---|---:|---:|")
    for p, rate in peaks.items():
        print(f"| {p} | {sizes[p]} | {rate:.1f} |")

    for name in args.presets:
        settings = settings_for(params, name)
        big = settings["size"] >= 256
        warmup, iterations = (args.paper_warmup, args.paper_iterations) if big else (args.warmup, args.iterations)
        counts = {m: (warmup, iterations) for m in methods}
        if "vtgen bf16" in counts:
            slow = (warmup, iterations) if native else (min(warmup, 1), min(iterations, 2))
            counts["vtgen bf16"] = (slow[0] if args.bf16_warmup is None else args.bf16_warmup,
                                    slow[1] if args.bf16_iterations is None else args.bf16_iterations)
        benchmark(name, settings, methods, peaks, counts, args.repeats, args.tiles, args.profile)
    print(f"\nload average after: {load_average()}")


if __name__ == "__main__":
    main()
