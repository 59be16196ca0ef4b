"""Benchmark: ingest and ROI throughput and memory on ViTac-style 256x256 JPEG tiles, at several sizes.

Writes ViTac-layout JPEG tiles (rendered SYNTHETIC fabric, re-encoded as JPEG at quality 95 like
the ViTac tiles) into a temporary folder, once for the largest size; each smaller size links the
first N files. For each size a fresh Python process (so memory figures are its own) times the
ingest stage (full decode + hash of every file) and the ROI stage (decode, crop, resize, PNG
write), median of ``--repeats`` runs, and prints one markdown table row:

* ingest / ROI / ingest+ROI images per second (wall clock; N / median seconds);
* CPU ms per image of ingest + ROI (process CPU time over all threads, divided by N): less
  sensitive than the wall clock to other programs sharing the cores;
* peak RSS of the child (``ru_maxrss``) and its growth over the same process after imports and a
  50-image warm-up: memory that streams stays flat in N (the tables hold a few hundred bytes of
  metadata per image; 16,000 images of 256x256 RGB would be 3 GB of pixels).

ROI settings (``--roi``): ``plain`` (default; the earlier benchmark: whole frame, no marker removal,
resize 256 -> 64 px) or ``params`` (the ``roi`` section of params.yaml: the main job's settings,
with GelSight marker removal on the tactile half, much slower per image).

    python benchmarks/data_throughput.py --sizes 1000 4000 16000 --workers 2 --repeats 3
    python benchmarks/data_throughput.py --sizes 500 2000 --roi params --repeats 1
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
PLAIN_ROI = {"size": 64, "tactile_box": "full", "remove_markers": False, "visual_crop": "centre", "crop_fraction": 1.0}


def image_name(i: int) -> str:
    """Relative path of the i-th tile: even i tactile (``1t/<frame>_<tile>.jpg``), odd i visual."""
    return f"1t/{i // 8}_{i % 8}.jpg" if i % 2 == 0 else f"1v/IMG_1_{i}.jpg"


def write_vitac_like(root: Path, images: int, seed: int = 0) -> None:
    """``images`` JPEG tiles in ViTac folders (half tactile, half visual) for cloth 1."""
    from vtgen.core.synthetic import FABRICS, render_gelsight, render_patch, render_visual

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
        cv2.imwrite(str(root / image_name(i)), cv2.cvtColor(noisy, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 95])


def link_subset(full: Path, root: Path, images: int) -> None:
    """The first ``images`` tiles of ``full`` as hard links under ``root`` (no copying)."""
    (root / "1t").mkdir(parents=True)
    (root / "1v").mkdir(parents=True)
    for i in range(images):
        os.link(full / image_name(i), root / image_name(i))


def max_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def child(root: Path, work: Path, images: int, workers: int, repeats: int, roi: dict) -> dict:
    """Run in a fresh process: time ingest and ROI on ``root``; return medians and memory."""
    from vtgen.stages.ingest import ingest_dataset
    from vtgen.stages.roi import cut_dataset_tiles

    warm = work / "warm"
    link_subset(root, warm / "raw", min(50, images))
    manifest, _, _ = ingest_dataset(warm / "raw", "vitac", workers=workers, progress=False)
    cut_dataset_tiles(manifest, roi, warm / "tiles", workers=workers, progress=False)
    del manifest
    baseline = max_rss_mb()
    runs = []
    for repeat in range(repeats):
        cpu, start = time.process_time(), time.perf_counter()
        manifest, _, _ = ingest_dataset(root, "vitac", workers=workers, progress=False)
        ingest_s, ingest_cpu = time.perf_counter() - start, time.process_time() - cpu
        assert len(manifest) == images, (len(manifest), images)
        cpu, start = time.process_time(), time.perf_counter()
        tiles = cut_dataset_tiles(manifest, roi, work / f"tiles{repeat}", workers=workers, progress=False)
        roi_s, roi_cpu = time.perf_counter() - start, time.process_time() - cpu
        assert len(tiles) >= images
        runs.append((ingest_s, roi_s, ingest_s + roi_s, ingest_cpu + roi_cpu))
        del manifest, tiles
    ingest_s, roi_s, both_s, cpu_s = (float(np.median(column)) for column in zip(*runs))
    return {"images": images, "ingest_s": ingest_s, "roi_s": roi_s, "both_s": both_s, "cpu_s": cpu_s,
            "baseline_rss_mb": baseline, "peak_rss_mb": max_rss_mb()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 4000, 16000], help="numbers of images")
    parser.add_argument("--images", type=int, help="one size (same as --sizes N)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--roi", choices=["plain", "params"], default="plain",
                        help="plain: whole frame to 64 px, no marker removal; params: params.yaml's roi section")
    parser.add_argument("--child", nargs=2, metavar=("ROOT", "WORK"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.roi == "plain":
        roi = PLAIN_ROI
    else:
        import yaml

        roi = yaml.safe_load((REPO / "params.yaml").read_text())["roi"]
    if args.child:
        result = child(Path(args.child[0]), Path(args.child[1]), args.images, args.workers, args.repeats, roi)
        print(json.dumps(result))
        return
    sizes = [args.images] if args.images else sorted(args.sizes)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        full = Path(tmp) / "full"
        started = time.perf_counter()
        write_vitac_like(full, max(sizes))
        print(f"wrote {max(sizes)} tiles in {time.perf_counter() - started:.1f} s", file=sys.stderr)
        for n in sizes:
            root = Path(tmp) / f"vitac{n}"
            link_subset(full, root, n)
            work = Path(tmp) / f"work{n}"
            work.mkdir()
            cmd = [sys.executable, __file__, "--child", str(root), str(work), "--images", str(n),
                   "--workers", str(args.workers), "--repeats", str(args.repeats), "--roi", args.roi]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                sys.exit(f"child for {n} images failed:\n{done.stderr[-3000:]}")
            rows.append(json.loads(done.stdout.strip().splitlines()[-1]))
            print(f"{n} images done", file=sys.stderr)
    print(f"ViTac-style 256x256 JPEG tiles; ROI settings '{args.roi}': {json.dumps(roi)}; "
          f"{args.workers} workers on {os.cpu_count()} cores; median of {args.repeats} run(s) per size, "
          f"each size in its own process")
    print()
    print("| images | ingest img/s | ROI img/s | ingest+ROI img/s | CPU ms/img (ingest+ROI) | peak RSS MB | RSS growth over warm-up MB |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        n = r["images"]
        print(f"| {n:,} | {n / r['ingest_s']:,.0f} | {n / r['roi_s']:,.0f} | {n / r['both_s']:,.0f} | "
              f"{1e3 * r['cpu_s'] / n:.2f} | {r['peak_rss_mb']:.0f} | {r['peak_rss_mb'] - r['baseline_rss_mb']:.0f} |")


if __name__ == "__main__":
    main()
