"""Render stage: write the embedded SYNTHETIC ViTac-like dataset in the generic layout.

The pictures come from :mod:`vtgen.core.synthetic`; this module only schedules the samples
over worker processes and writes them atomically.
"""

from __future__ import annotations

import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Sequence

import cv2
from tqdm import tqdm

from vtgen.core.synthetic import FABRICS, MIN_SIZE, render_gelsight, render_patch, render_visual, sample_rngs
from vtgen.io.images import atomic_output_dir, write_png


def _render_sample(job: tuple[str, str, int, int, int, bool, int]) -> None:
    """Render and write one sample (worker entry point; module level so it pickles)."""
    root, fabric, class_index, index, size, aligned, seed = job
    g_patch_v, g_patch_t, g_vis, g_tac = sample_rngs(seed, class_index, index)
    patch_v = render_patch(fabric, size, g_patch_v)
    patch_t = patch_v if aligned else render_patch(fabric, size, g_patch_t)
    vis_name, tac_name = (f"s{index:04d}", f"s{index:04d}") if aligned else (f"v{index:04d}", f"t{index:04d}")
    base = Path(root) / fabric
    write_png(base / "visual" / f"{vis_name}.png", render_visual(patch_v, g_vis))
    write_png(base / "tactile" / f"{tac_name}.png", render_gelsight(patch_t, g_tac))


def _init_worker() -> None:
    cv2.setNumThreads(1)  # one process per core; no nested thread pools


def render_dataset(
    out_dir: Path,
    classes: Sequence[str],
    samples_per_class: int,
    size: int,
    aligned: bool,
    seed: int,
    workers: int = 2,
    progress: bool = True,
) -> dict:
    """Render the synthetic dataset into `out_dir` in the generic layout.

    Writes ``<class>/visual/<name>.png`` and ``<class>/tactile/<name>.png`` (8-bit RGB) and
    ``dataset.json``. Aligned: sample i is ``s<i:04d>`` in both modalities (same patch, same
    view). Unaligned: ``v<i:04d>`` and ``t<i:04d>`` from independent patches of the class.
    Output is built in a temporary sibling and renamed into place at the end, replacing any old
    `out_dir` (:func:`vtgen.imageio.atomic_output_dir`). Sample i of a class draws from SeedSequence([seed, FABRICS.index(class), i]),
    so the files do not depend on `workers`. Returns the dataset.json dict plus "seconds".
    """
    t0 = time.perf_counter()
    classes = list(classes)
    unknown = [c for c in classes if c not in FABRICS]
    if unknown or not classes:
        raise ValueError(f"unknown classes {unknown}; valid names: {', '.join(FABRICS)}" if unknown
                         else f"no classes given; valid names: {', '.join(FABRICS)}")
    if len(set(classes)) != len(classes):
        raise ValueError(f"duplicate class names in {classes}")
    if int(samples_per_class) != samples_per_class or samples_per_class < 1:
        raise ValueError(f"samples_per_class must be a positive integer, got {samples_per_class!r}")
    if int(size) != size or size < MIN_SIZE:
        raise ValueError(f"size must be an integer >= {MIN_SIZE}, got {size!r}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers!r}")

    info = {
        "synthetic": True,
        "generator": "vtgen.synthetic",
        "aligned": bool(aligned),
        "seed": int(seed),
        "size": int(size),
        "samples_per_class": int(samples_per_class),
        "classes": classes,
    }
    with atomic_output_dir(out_dir) as tmp:
        for c in classes:
            (tmp / c / "visual").mkdir(parents=True)
            (tmp / c / "tactile").mkdir(parents=True)
        jobs = [(str(tmp), c, FABRICS.index(c), i, int(size), bool(aligned), int(seed))
                for c in classes for i in range(int(samples_per_class))]
        with tqdm(total=len(jobs), desc="render synthetic", unit="sample", disable=not progress) as bar:
            if workers == 1:
                for job in jobs:
                    _render_sample(job)
                    bar.update()
            else:
                # spawn, not fork: a forked child inherits OpenCV's thread pool in a locked state
                context = multiprocessing.get_context("spawn")
                with ProcessPoolExecutor(workers, mp_context=context, initializer=_init_worker) as pool:
                    try:
                        for _ in pool.map(_render_sample, jobs, chunksize=4):
                            bar.update()
                    finally:  # after an error, the shutdown's cancel (vtgen.io.images._stream says why)
                        pool.shutdown(wait=True, cancel_futures=True)
        (tmp / "dataset.json").write_text(json.dumps(info, indent=2) + "\n")
    return {**info, "seconds": round(time.perf_counter() - t0, 3)}
