"""Training images per second of the classify stage's network by batch size, in one process on one thread.

The bare training step (forward, cross-entropy, backward, Adam) of ``AlexNet(10 classes, 64 px, width 0.25)``
(the default ``classify`` block) on random channels-last inputs already scaled, at each batch size and
precision; no data loading, evaluation or batch-norm refresh. It bounds what the classify stage's loop can
reach per core: the stage's own images/s (``summary.json``, ``speed``) over this table's rate at its batch
size is the loop's overhead.

    python benchmarks/classify_batch_size.py                       # fp32 and bf16, batches 32 64 128 256
    python benchmarks/classify_batch_size.py --precisions bf16 --batches 32 256 --images 3072
"""

from __future__ import annotations

import argparse
import platform
import time

import torch
import torch.nn.functional as F

from vtgen.core.classifier import AlexNet


def images_per_second(batch: int, precision: str, images: int, warmup: int = 3) -> float:
    """Training images per second of ``images`` images (at least 3 steps) after ``warmup`` untimed steps."""
    torch.manual_seed(0)
    model = AlexNet(10, 64, 0.25)
    optimiser = torch.optim.Adam(model.parameters(), 1e-3)
    x = torch.randn(batch, 3, 64, 64).contiguous(memory_format=torch.channels_last)
    y = torch.randint(0, 10, (batch,))

    def step() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=precision == "bf16"):
            logits = model.scaled_forward(x)
        loss = F.cross_entropy(logits.float(), y)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()

    for _ in range(warmup):
        step()
    steps = max(3, images // batch)
    start = time.perf_counter()
    for _ in range(steps):
        step()
    return steps * batch / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", type=int, nargs="+", default=[32, 64, 128, 256])
    parser.add_argument("--precisions", nargs="+", choices=["fp32", "bf16"], default=["fp32", "bf16"])
    parser.add_argument("--images", type=int, default=1536, help="timed training images per cell")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"{platform.processor() or platform.machine()}, torch {torch.__version__}, 1 thread")
    print("| precision | " + " | ".join(f"batch {b}" for b in args.batches) + " |")
    print("|---|" + "---|" * len(args.batches))
    for precision in args.precisions:
        rates = [images_per_second(b, precision, args.images) for b in args.batches]
        print(f"| {precision} | " + " | ".join(f"{r:,.0f} images/s" for r in rates) + " |")


if __name__ == "__main__":
    main()
