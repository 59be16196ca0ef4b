"""Benchmark: ingest and ROI throughput on ViTac-style 256x256 JPEG tiles.

Writes N JPEG tiles in the ViTac layout (rendered SYNTHETIC fabric, re-encoded as JPEG at
quality 95 like the ViTac tiles) into a temporary folder, then times the ingest stage
(full decode + hash of every file) and the ROI stage (decode, crop, resize, PNG write).

    python benchmarks/data_throughput.py --images 2000 --workers 2
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from vtgen.ingest import ingest_dataset
from vtgen.synthetic import FABRICS, render_gelsight, render_patch, render_visual
from vtgen.tiling import cut_dataset_tiles


def write_vitac_like(root: Path, images: int, seed: int = 0) -> None:
    """``images`` JPEG tiles in ViTac folders (half tactile, half visual) for cloth 1."""
    rng = np.random.default_rng(seed)
    bases = []
    for fabric in FABRICS[:4]:
        patch = render_patch(fabric, 256, rng)
        bases += [render_gelsight(patch, rng), render_visual(patch, rng)]
    (root / "1t").mkdir(parents=True)
    (root / "1v").mkdir(parents=True)
    for i in range(images):
        base = bases[i % len(bases)]
        noisy = np.clip(base.astype(np.int16) + rng.integers(-3, 4, base.shape), 0, 255).astype(np.uint8)
        name = root / ("1t" if i % 2 == 0 else "1v") / (f"{i // 8}_{i % 8}.jpg" if i % 2 == 0 else f"IMG_1_{i}.jpg")
        cv2.imwrite(str(name), cv2.cvtColor(noisy, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    roi = {"size": 64, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 1.0}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "vitac"
        write_vitac_like(root, args.images)
        rows = []
        for repeat in range(args.repeats):
            start = time.perf_counter()
            manifest, _, _ = ingest_dataset(root, "vitac", workers=args.workers, progress=False)
            ingest_s = time.perf_counter() - start
            start = time.perf_counter()
            cut_dataset_tiles(manifest, roi, Path(tmp) / f"tiles{repeat}", workers=args.workers, progress=False)
            roi_s = time.perf_counter() - start
            rows.append((ingest_s, roi_s))
    ingest_s, roi_s = (float(np.median(c)) for c in zip(*rows))
    n = args.images
    print(f"{n} ViTac-style 256x256 JPEG tiles, {args.workers} workers, median of {args.repeats} runs")
    print(f"| stage        | seconds | images/s |")
    print(f"|--------------|--------:|---------:|")
    print(f"| ingest       | {ingest_s:7.2f} | {n / ingest_s:8.0f} |")
    print(f"| roi (64 px)  | {roi_s:7.2f} | {n / roi_s:8.0f} |")
    print(f"| ingest + roi | {ingest_s + roi_s:7.2f} | {n / (ingest_s + roi_s):8.0f} |")


if __name__ == "__main__":
    main()
