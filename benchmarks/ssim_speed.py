"""Milliseconds per image pair of vtgen.metrics.colour_ssim against scikit-image's structural_similarity.

Image pairs are smooth random textures and noisy copies of them (uint8, channels last), so the
scores sit in the range real comparisons give. Per image:

- scikit-image: ``structural_similarity(x, y, channel_axis=-1, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=255)`` in a Python loop over the pairs;
- vtgen ``colour_ssim`` on the whole batch, computing in float64 (the default) and in float32.

Set-to-set (every image of one set against every image of another, ``--set N``):
``pairwise_colour_ssim`` on N x N pairs against the naive scikit-image double loop, which is
timed on a ``--skimage-set`` x ``--skimage-set`` subset and given per pair (its cost per pair does
not depend on N). Every time is the median of ``--repeats`` runs after one warm-up run; "max |diff|"
is the largest absolute difference from scikit-image's scores on the pairs both computed.

Allocator warm-up: glibc's malloc serves blocks above its mmap threshold (128 KiB at start) with
fresh pages, so each one is page-faulted in again, and it raises that threshold only when such
a block smaller than 32 MiB is freed. Right after the input arrays are built (all larger than
32 MiB) every 0.5 MiB temporary of scikit-image faults, and it runs about twice as slowly as in
a process that has freed a mid-sized array once, which is the usual case. The script times
scikit-image once in that cold state (printed below the table, not used for the ratios), then
frees a 16 MiB array and times everything warm: the speed-ups are against scikit-image at its best.

    python benchmarks/ssim_speed.py                    # 64 pairs of 256x256x3, torch threads = 2
    python benchmarks/ssim_speed.py --pairs 16 --size 128 --repeats 3
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np
import torch
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from vtgen.metrics import colour_ssim, pairwise_colour_ssim


def textured_pairs(n: int, size: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """n smooth random RGB textures and noisy copies, uint8 (n, size, size, 3)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(n, size, size, 3))
    texture = gaussian_filter(noise, sigma=(0, 3, 3, 0))
    texture = 128 + 100 * texture / texture.std()
    a = np.clip(texture, 0, 255).round().astype(np.uint8)
    b = np.clip(texture + rng.normal(0, 15, texture.shape), 0, 255).round().astype(np.uint8)
    return a, b


def skimage_ssim(x: np.ndarray, y: np.ndarray) -> float:
    return structural_similarity(x, y, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=255)


def median_seconds(function, repeats: int):
    """(median wall time over ``repeats`` runs after one warm-up, the last result)."""
    result = function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=64, help="image pairs per batch")
    parser.add_argument("--size", type=int, default=256, help="image side (square, 3 channels)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    parser.add_argument("--set", type=int, default=32, help="set-to-set: N x N pairs for pairwise_colour_ssim")
    parser.add_argument("--skimage-set", type=int, default=6,
                        help="set-to-set: subset side for the skimage double loop")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    a, b = textured_pairs(max(args.pairs, args.set), args.size)
    cold = min(8, args.pairs)
    start = time.perf_counter()
    for i in range(cold):
        skimage_ssim(a[i], b[i])
    cold_ms = 1e3 * (time.perf_counter() - start) / cold
    np.ones(2 << 20)  # allocate and free 16 MiB: glibc now keeps blocks up to that size for reuse
    print(f"CPU: {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"{torch.get_num_threads()} torch threads; images {args.size}x{args.size}x3 uint8; "
          f"median of {args.repeats} runs\n")
    print("| method | pairs | ms per pair | speed-up vs scikit-image | max abs diff vs scikit-image |")
    print("|---|---|---|---|---|")

    n = args.pairs
    seconds, reference = median_seconds(lambda: np.array([skimage_ssim(a[i], b[i]) for i in range(n)]), args.repeats)
    skimage_ms = 1e3 * seconds / n
    print(f"| scikit-image structural_similarity, loop | {n} | {skimage_ms:.2f} | 1.0x | 0 |", flush=True)
    for dtype in (torch.float64, torch.float32):
        seconds, scores = median_seconds(lambda: colour_ssim(a[:n], b[:n], dtype=dtype), args.repeats)
        ms = 1e3 * seconds / n
        print(f"| vtgen colour_ssim, batched, {str(dtype).removeprefix('torch.')} | {n} | {ms:.2f} | "
              f"{skimage_ms / ms:.1f}x | {np.abs(scores - reference).max():.1e} |", flush=True)

    k, s = args.set, min(args.skimage_set, args.set)
    seconds, reference = median_seconds(
        lambda: np.array([[skimage_ssim(a[i], b[j]) for j in range(s)] for i in range(s)]), args.repeats)
    skimage_pair_ms = 1e3 * seconds / (s * s)
    print(f"| set-to-set: scikit-image double loop (timed on {s}x{s}, per pair) | {s * s} | "
          f"{skimage_pair_ms:.2f} | 1.0x | 0 |", flush=True)
    for dtype in (torch.float64, torch.float32):
        seconds, matrix = median_seconds(lambda: pairwise_colour_ssim(a[:k], b[:k], dtype=dtype), args.repeats)
        ms = 1e3 * seconds / (k * k)
        print(f"| set-to-set: vtgen pairwise_colour_ssim {k}x{k}, {str(dtype).removeprefix('torch.')} | {k * k} | "
              f"{ms:.2f} | {skimage_pair_ms / ms:.1f}x | {np.abs(matrix[:s, :s] - reference).max():.1e} |", flush=True)
    print(f"\nscikit-image before the allocator warm-up (cold glibc malloc, {cold} pairs, one run): "
          f"{cold_ms:.2f} ms per pair")


if __name__ == "__main__":
    main()
