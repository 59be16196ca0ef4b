"""Milliseconds per image pair of vtgen.core.metrics.colour_ssim against scikit-image's structural_similarity.

Image pairs are smooth random textures and noisy copies of them (uint8, channels last), so the
scores sit in the range real comparisons give. Methods, each on the same ``--batch`` pairs:

- scikit-image: ``structural_similarity(x, y, channel_axis=-1, gaussian_weights=True, sigma=1.5,
  use_sample_covariance=False, data_range=255)`` in a Python loop over the pairs;
- numba float64: ``colour_ssim`` (the fused kernel, vtgen's one SSIM implementation), batched,
  on one thread (per-core efficiency, comparable with the single-threaded scikit-image) and on
  ``--threads``.

Set-to-set (every image of one set against every image of another, ``--set N``): the naive
scikit-image double loop, timed on a ``--skimage-set`` x ``--skimage-set`` subset and given per
pair (its cost per pair does not depend on N), against ``pairwise_colour_ssim`` on N x N pairs
(numba).

Timing: one warm-up run of every method, then ``--repeats`` rounds that run the methods one
after the other (interleaved, so a change in machine load hits them alike, with a 20 ms pause
before each so that idle OpenMP threads of the previous one stop spinning); each time is the
median over the rounds, and the speed-ups are ratios of medians from the same run. "max abs
diff" is the largest absolute difference from scikit-image's scores on the pairs both computed.

First call: the kernel is compiled by numba on first use and cached on disk. The script times a
first call in a fresh Python process with an empty cache directory (compiling), and in a second
one with that cache (loading), for uint8 input.

Allocator warm-up: glibc's malloc serves blocks above its mmap threshold (128 KiB at start) with
fresh pages, so each one is page-faulted in again, and it raises that threshold only when such
a block smaller than 32 MiB is freed. Right after the input arrays are built every 0.5 MiB
temporary of scikit-image faults, and it runs about twice as slowly as in a process that has
freed a mid-sized array once, the usual case. The script frees a 16 MiB array before timing:
the speed-ups are against scikit-image at its best.

    python benchmarks/ssim_speed.py                          # 64 pairs of 256x256x3, 2 threads
    python benchmarks/ssim_speed.py --batch 16 --size 128 --repeats 5 --set 8
    python benchmarks/ssim_speed.py --quick                  # 16 pairs of 128x128x3, 3 rounds, set 8
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np
from scipy.ndimage import gaussian_filter
from skimage.metrics import structural_similarity

from vtgen.core.metrics import colour_ssim, pairwise_colour_ssim

FIRST_CALL = """
import time
import numpy as np
start = time.perf_counter()
from vtgen.core.metrics import colour_ssim
imported = time.perf_counter()
colour_ssim(np.zeros((1, {size}, {size}, 3), np.uint8), np.full((1, {size}, {size}, 3), 9, np.uint8))
print(imported - start, time.perf_counter() - imported)
"""


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


def interleaved_medians(methods: dict, repeats: int) -> tuple[dict[str, float], dict]:
    """Median wall time of each method over ``repeats`` interleaved rounds after one warm-up
    round, and each method's last result."""
    results = {name: function() for name, function in methods.items()}
    times: dict[str, list[float]] = {name: [] for name in methods}
    for _ in range(repeats):
        for name, function in methods.items():
            time.sleep(0.02)  # let the previous method's worker threads stop spinning
            start = time.perf_counter()
            results[name] = function()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}, results


def first_call_seconds(size: int) -> tuple[tuple[float, float], tuple[float, float]]:
    """(import, first call) seconds in a fresh process: with an empty numba cache, then with it."""
    runs = []
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        for _ in range(2):
            out = subprocess.run([sys.executable, "-c", FIRST_CALL.format(size=size)], env=env, check=True,
                                 capture_output=True, text=True).stdout.split()
            runs.append((float(out[0]), float(out[1])))
    return runs[0], runs[1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", "--pairs", dest="batch", type=int, default=64,
                        help="image pairs per batch (skimage loops over them)")
    parser.add_argument("--size", type=int, default=256, help="image side (square, 3 channels)")
    parser.add_argument("--repeats", type=int, default=5, help="interleaved timing rounds (median)")
    parser.add_argument("--threads", type=int, default=2, help="numba threads")
    parser.add_argument("--set", type=int, default=16, help="set-to-set: N x N pairs for pairwise_colour_ssim")
    parser.add_argument("--skimage-set", type=int, default=4,
                        help="set-to-set: subset side for the skimage double loop (and the diff)")
    parser.add_argument("--no-first-call", action="store_true", help="skip timing the compilation in subprocesses")
    parser.add_argument("--quick", action="store_true",
                        help="a short run: --batch 16 --size 128 --repeats 3 --set 8 --no-first-call")
    args = parser.parse_args()
    if args.quick:
        args.batch, args.size, args.repeats, args.set, args.no_first_call = 16, 128, 3, 8, True
    threads = min(args.threads, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(threads)

    def one_thread(function, *arguments):
        numba.set_num_threads(1)
        try:
            return function(*arguments)
        finally:
            numba.set_num_threads(threads)

    n, k = args.batch, args.set
    s = min(args.skimage_set, k)
    a, b = textured_pairs(max(n, k), args.size)
    colour_ssim(a[:1], b[:1])  # compile or load the kernel before anything is timed
    np.ones(2 << 20)  # allocate and free 16 MiB: glibc now keeps blocks up to that size for reuse

    per_pair = {
        "scikit-image structural_similarity, loop": (n, lambda: np.array([skimage_ssim(a[i], b[i]) for i in range(n)])),
        "numba float64 fused kernel (colour_ssim), batched, 1 thread": (n, lambda: one_thread(colour_ssim, a[:n], b[:n])),
        f"numba float64 fused kernel (colour_ssim), batched, {threads} threads": (n, lambda: colour_ssim(a[:n], b[:n])),
    }
    set_to_set = {
        f"set-to-set: scikit-image double loop ({s}x{s})": (s * s, lambda: np.array(
            [[skimage_ssim(a[i], b[j]) for j in range(s)] for i in range(s)])),
        f"set-to-set: numba pairwise_colour_ssim, {k}x{k}": (k * k, lambda: pairwise_colour_ssim(a[:k], b[:k])),
    }
    methods = {name: function for name, (_, function) in {**per_pair, **set_to_set}.items()}
    seconds, results = interleaved_medians(methods, args.repeats)

    print(f"CPU: {platform.processor() or platform.machine()}, {os.cpu_count()} cores; "
          f"numba {numba.__version__}, {threads} numba threads; images {args.size}x{args.size}x3 uint8; "
          f"median of {args.repeats} interleaved rounds\n")
    print("| method | pairs | ms per pair | x vs scikit-image | max abs diff vs scikit-image |")
    print("|---|---|---|---|---|")
    for table in (per_pair, set_to_set):
        names = list(table)
        reference_ms = 1e3 * seconds[names[0]] / table[names[0]][0]
        reference = results[names[0]]
        for name in names:
            pairs = table[name][0]
            ms = 1e3 * seconds[name] / pairs
            result = np.asarray(results[name])
            diff = np.abs((result[:s, :s] if result.ndim == 2 else result) - reference).max()
            print(f"| {name} | {pairs} | {ms:.3f} | {reference_ms / ms:.1f}x | {diff:.1e} |")
    print(f"\nthreading layer: {numba.threading_layer()}")
    if not args.no_first_call:
        (import_cold, cold), (import_warm, warm) = first_call_seconds(args.size)
        print(f"first call of colour_ssim in a fresh process (one {args.size}x{args.size}x3 uint8 pair): "
              f"{cold:.2f} s with an empty numba cache (compiling), {warm:.2f} s with the cache (loading); "
              f"importing vtgen.core.metrics: {import_cold:.2f} s / {import_warm:.2f} s")


if __name__ == "__main__":
    main()
