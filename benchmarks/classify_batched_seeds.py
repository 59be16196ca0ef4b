"""Would training the classify seeds together as one grouped model be faster on this CPU? A probe.

One training step (forward, backward, Adam) of the classify stage's AlexNet (params.yaml's classify
size and width, batch 32, fp32, torch threads 1) for S seeds: S separate models stepped one after
the other (what the stage does) against one model holding the S networks side by side (every
convolution with ``groups=S`` over the S seeds' stacked channels, every linear layer one batched
matrix product, one Adam over all). The two do the same arithmetic per seed; only the kernels
differ. A third way stacks the S models' parameters and buffers and maps one model's step over them
(``torch.func.vmap`` of ``functional_call``, dropout drawn per seed). A fourth compiles each separate model's
forward with ``torch.compile`` (inductor; its compile seconds are printed, not counted in the step). ``--precision bf16`` runs every
way under bf16 autocast (what ``classify.precision: auto`` picks on a CPU with AVX512-BF16 or AMX).
Prints a markdown table of seconds per step (median of ``--steps``, interleaved rounds).

    python benchmarks/classify_batched_seeds.py --seeds 3 --steps 20 --rounds 3 --precision bf16
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
import yaml
from torch import nn
from torch.func import functional_call, stack_module_state, vmap

from vtgen.core.classifier import BASE_CHANNELS, BASE_HIDDEN, MIN_CHANNELS, AlexNet, feature_side, first_conv

REPO = Path(__file__).resolve().parents[1]


class GroupedAlexNet(nn.Module):
    """``seeds`` AlexNets (no dropout differences in the arithmetic) side by side in one module."""

    def __init__(self, seeds: int, num_classes: int, size: int, width: float):
        super().__init__()
        channels = [max(MIN_CHANNELS, round(c * width)) for c in BASE_CHANNELS]
        hidden = max(MIN_CHANNELS, round(BASE_HIDDEN * width))
        kernel, stride, padding = first_conv(size)
        shapes = [(3, channels[0], kernel, stride, padding), (channels[0], channels[1], 5, 1, 2),
                  (channels[1], channels[2], 3, 1, 1), (channels[2], channels[3], 3, 1, 1),
                  (channels[3], channels[4], 3, 1, 1)]
        layers: list[nn.Module] = []
        for i, (c_in, c_out, k, s, p) in enumerate(shapes, start=1):
            layers += [nn.Conv2d(c_in * seeds, c_out * seeds, k, s, p, groups=seeds, bias=False),
                       nn.BatchNorm2d(c_out * seeds), nn.ReLU(inplace=True)]
            if i in (1, 2, 5):
                layers.append(nn.MaxPool2d(3, 2))
        self.seeds, self.last = seeds, channels[4]
        self.side = min(6, feature_side(size))
        self.features, self.pool = nn.Sequential(*layers), nn.AdaptiveAvgPool2d(self.side)
        inputs = channels[4] * self.side ** 2
        self.fc6 = nn.Parameter(torch.randn(seeds, inputs, hidden) / inputs ** 0.5)
        self.fc7 = nn.Parameter(torch.randn(seeds, hidden, hidden) / hidden ** 0.5)
        self.fc8 = nn.Parameter(torch.randn(seeds, hidden, num_classes) / hidden ** 0.5)
        self.to(memory_format=torch.channels_last)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``batch x (seeds * 3) x H x W`` (seed s's images in channels 3s..3s+2) -> ``seeds x batch x classes``."""
        h = self.pool(self.features(x)).reshape(len(x), self.seeds, -1).transpose(0, 1)
        h = F.relu(torch.bmm(F.dropout(h, 0.5), self.fc6))
        h = F.relu(torch.bmm(F.dropout(h, 0.5), self.fc7))
        return torch.bmm(h, self.fc8)


class ScaledAlexNet(AlexNet):
    """AlexNet whose ``forward`` takes scaled tiles (``scaled_forward``), for ``functional_call``."""

    def forward(self, scaled: torch.Tensor) -> torch.Tensor:
        return self.scaled_forward(scaled)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--precision", choices=["fp32", "bf16"], default="fp32")
    args = parser.parse_args()
    cfg = yaml.safe_load((REPO / "params.yaml").read_text())["classify"]
    torch.set_num_threads(1)
    size, width, batch, classes, seeds = cfg["size"], cfg["width"], cfg["batch_size"], 10, args.seeds
    torch.manual_seed(0)
    separate = [AlexNet(classes, size, width) for _ in range(seeds)]
    optimisers = [torch.optim.Adam(m.parameters(), lr=cfg["lr"]) for m in separate]
    grouped = GroupedAlexNet(seeds, classes, size, width)
    grouped_optimiser = torch.optim.Adam(grouped.parameters(), lr=cfg["lr"])
    images = [torch.rand(batch, 3, size, size).mul(2).sub(1).contiguous(memory_format=torch.channels_last)
              for _ in range(seeds)]
    labels = [torch.randint(0, classes, (batch,)) for _ in range(seeds)]
    stacked = torch.cat(images, dim=1).contiguous(memory_format=torch.channels_last)
    stacked_labels = torch.cat(labels)
    mapped_params, mapped_buffers = stack_module_state([ScaledAlexNet(classes, size, width) for _ in range(seeds)])
    template = ScaledAlexNet(classes, size, width).to("meta")
    mapped_optimiser = torch.optim.Adam(list(mapped_params.values()), lr=cfg["lr"])
    per_seed_images, per_seed_labels = torch.stack(images), torch.stack(labels)

    def seed_loss(params, buffers, x, y):
        return F.cross_entropy(functional_call(template, (params, buffers), (x,)), y)

    mapped_loss = vmap(seed_loss, randomness="different")
    compiled_models = [AlexNet(classes, size, width) for _ in range(seeds)]
    compiled_optimisers = [torch.optim.Adam(m.parameters(), lr=cfg["lr"]) for m in compiled_models]
    compiled_forwards = [torch.compile(m.scaled_forward) for m in compiled_models]
    autocast = torch.autocast("cpu", dtype=torch.bfloat16, enabled=args.precision == "bf16")

    def step_separate():
        for model, optimiser, x, y in zip(separate, optimisers, images, labels):
            with autocast:
                loss = F.cross_entropy(model.scaled_forward(x), y)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()

    def step_grouped():
        # the sum over seeds of each seed's mean loss: each seed's gradient is its own
        with autocast:
            loss = F.cross_entropy(grouped(stacked).reshape(seeds * batch, classes).float(), stacked_labels) * seeds
        grouped_optimiser.zero_grad(set_to_none=True)
        loss.backward()
        grouped_optimiser.step()

    def step_mapped():
        with autocast:
            loss = mapped_loss(mapped_params, mapped_buffers, per_seed_images, per_seed_labels).sum()
        mapped_optimiser.zero_grad(set_to_none=True)
        loss.backward()
        mapped_optimiser.step()

    def step_compiled():
        for forward, optimiser, x, y in zip(compiled_forwards, compiled_optimisers, images, labels):
            with autocast:
                loss = F.cross_entropy(forward(x), y)
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()

    started = time.perf_counter()
    step_compiled()  # the first call compiles (forward and backward graphs)
    compile_seconds = time.perf_counter() - started
    times = {"separate models, one after the other": [], "one grouped model": [], "vmap over stacked models": [],
             "separate models, torch.compile": []}
    for _ in range(args.rounds):
        for name, step in zip(times, (step_separate, step_grouped, step_mapped, step_compiled)):
            for _ in range(3):
                step()
            for _ in range(args.steps):
                started = time.perf_counter()
                step()
                times[name].append(time.perf_counter() - started)
    print(f"{seeds} seeds, {size} px, width {width}, batch {batch} per seed, {args.precision}, 1 torch thread; load "
          f"average (1 min) {os.getloadavg()[0]:.1f}; `python benchmarks/classify_batched_seeds.py --seeds {seeds} "
          f"--steps {args.steps} --rounds {args.rounds} --precision {args.precision}`\n")
    print("| training step of all seeds | median s | images/s |")
    print("|---|---:|---:|")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"| {name} | {median:.4f} | {seeds * batch / median:.0f} |")
    print(f"\ntorch.compile: first step (compiling {seeds} models) {compile_seconds:.1f} s")


if __name__ == "__main__":
    main()
