"""Seconds per training iteration of each preset, fp32 and bf16, through the real training loop.

Each measurement runs ``train_translator`` on random in-memory pairs (no disk reads) twice, for
``--warmup`` and for ``--warmup + --iterations`` steps, and reports the difference divided by
``--iterations``: first-step costs (allocation, autocast set-up) cancel out. An iteration is one
discriminator and one generator step on a batch of the preset's size, with random positioning.

    python benchmarks/train_speed.py                       # every preset in params.yaml
    python benchmarks/train_speed.py --presets fast --iterations 50
"""

from __future__ import annotations

import argparse
import platform
import time

import torch

from vtgen.config import load_params
from vtgen.models import UNetGenerator, build_discriminator, count_parameters
from vtgen.train import PairData, train_translator


def random_pairs(size: int, n: int = 32) -> PairData:
    images = torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8)
    return PairData(images, images.flip(1), ["c"] * n, torch.ones(n, dtype=torch.bool), images, {"c": torch.arange(n)})


def seconds_per_iteration(settings: dict, run: dict, warmup: int, iterations: int) -> float:
    data = random_pairs(settings["size"])

    def timed(steps: int) -> float:
        start = time.perf_counter()
        train_translator(data, dict(settings, iterations=steps), run, "v2t", "all", progress=False)
        return time.perf_counter() - start

    return (timed(warmup + iterations) - timed(warmup)) / iterations


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--presets", nargs="*", help="preset names (default: all in params.yaml)")
    parser.add_argument("--precisions", nargs="*", default=["fp32", "bf16"])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--warmup", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=20)
    args = parser.parse_args()
    params = load_params(args.params)
    run = dict(params["translation"], device=args.device, checkpoint_every=10**9, log_every=10**9)
    device = torch.cuda.get_device_name() if args.device == "cuda" else f"{platform.processor() or 'CPU'}, {run['threads']} threads"
    print(f"device: {device}; torch {torch.__version__}; {args.iterations} timed iterations after {args.warmup} warm-up\n")
    print("| preset | size | ngf/ndf | discriminator | batch | G params | D params | precision | s/iteration | images/s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name in args.presets or list(params["presets"]):
        settings = params["presets"][name]
        g = count_parameters(UNetGenerator(settings["size"], settings["ngf"], settings["kernel"]))
        d = count_parameters(build_discriminator(settings["discriminator"], settings["size"], settings["ndf"],
                                                 settings["kernel"], settings["patch_layers"]))
        for precision in args.precisions:
            seconds = seconds_per_iteration(settings, dict(run, precision=precision), args.warmup, args.iterations)
            print(f"| {name} | {settings['size']} | {settings['ngf']}/{settings['ndf']} | {settings['discriminator']} | "
                  f"{settings['batch_size']} | {g / 1e6:.1f} M | {d / 1e6:.1f} M | {precision} | {seconds:.3f} | "
                  f"{settings['batch_size'] / seconds:.1f} |", flush=True)


if __name__ == "__main__":
    main()
