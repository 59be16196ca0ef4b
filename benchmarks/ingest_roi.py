"""Benchmark: ingest + ROI images/s on real round-sensor frames (vt60 touch) and on 256 px tiles.

Two data sets, each timed in a fresh Python process (``--repeats`` runs, median):

* ``vt60``: the 480 real touch frames of ../shared/data/vt60_subset (640x480 8-bit greyscale JPEG,
  a round optical tactile sensor), seen through symbolic links in the ``generic`` layout
  (``<class>/tactile/<instance>_<name>.jpg``, which old and new ingest both read; never copied),
  with its 240 photos (300x300 RGB) as the visual half, which the old ingest requires;
* ``tiles256``: ViTac-layout 256x256 JPEG tiles (rendered SYNTHETIC fabric, half GelSight-like,
  half visual; :func:`data_throughput.write_vitac_like`), ``--tiles`` of them, in a temporary folder.

ROI, of all images and of the tactile ones alone; settings: ``size 64``, ``tactile_box`` from ``--tactile-box`` (default ``auto``),
``remove_markers: true``, centre crop 0.5. Printed per data set: images/s of ingest, of ROI and of
both (N / median wall seconds), with ``--workers`` workers (default 2: ingest threads, ROI processes), and the CPU time per image
(process time, all threads and worker processes: the work done, which other jobs on a shared machine barely change) with
the rate it would give if the work had the cores to itself (an upper bound: it assumes the worker
threads never wait for each other).

Before/after: ``--ref REF`` also times the ``src/`` of a git ref (extracted with ``git archive``
into a temporary folder; the working tree is not touched) in the same way, interleaved, so a busy
machine hits both alike. ``--rounds N`` alternates the two N times (a fresh process each time) and
reports the median over the rounds, so a load that changes during the run hits both alike too;
``--only vt60`` skips the synthetic tiles (whose GelSight path takes most of the time).

    python benchmarks/ingest_roi.py --ref ad8e6b8 --repeats 3
    python benchmarks/ingest_roi.py --ref HEAD --repeats 3 --rounds 3 --only vt60
    python benchmarks/ingest_roi.py --tactile-box full
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
VT60 = REPO.parent / "shared/data/vt60_subset"


def link_vt60(root: Path) -> None:
    """The vt60 frames as ``root/<class>/<tactile|visual>/<instance>_<name>.jpg`` symbolic links."""
    for folder, modality in (("touch", "tactile"), ("vision", "visual")):
        for path in sorted((VT60 / folder).glob("*/*/*.jpg")):
            target = root / path.parts[-3] / modality / f"{path.parts[-2]}_{path.name}"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(path)


def cpu_seconds() -> float:
    """CPU time of this process (all threads) plus that of its finished child processes (the ROI
    stage's worker processes are joined, so counted, when it returns)."""
    times = os.times()
    return time.process_time() + times.children_user + times.children_system


def child(root: Path, layout: str, work: Path, workers: int, repeats: int, roi: dict) -> dict:
    """In a fresh process (whose ``vtgen`` is the one on PYTHONPATH): time ingest and ROI."""
    from vtgen.stages.ingest import ingest_dataset
    from vtgen.stages.roi import cut_dataset_tiles

    dataset = "generic" if layout == "vt60" else "vitac"
    runs = []
    for repeat in range(repeats + 1):  # the first run warms imports and caches, not timed
        start, cpu = time.perf_counter(), cpu_seconds()
        manifest, _, _ = ingest_dataset(root, dataset, workers=workers, progress=False)
        ingest_s, ingest_cpu = time.perf_counter() - start, cpu_seconds() - cpu
        start, cpu = time.perf_counter(), cpu_seconds()
        tiles = cut_dataset_tiles(manifest, roi, work / f"tiles{repeat}", workers=workers, progress=False)
        roi_s, roi_cpu = time.perf_counter() - start, cpu_seconds() - cpu
        assert len(tiles) >= len(manifest) - 5, (len(tiles), len(manifest))
        tactile = manifest[manifest["modality"] == "tactile"].reset_index(drop=True)
        start = time.perf_counter()
        cut_dataset_tiles(tactile, roi, work / f"tactile{repeat}", workers=workers, progress=False)
        tactile_s = time.perf_counter() - start
        if repeat:
            runs.append((ingest_s, roi_s, tactile_s, ingest_cpu, roi_cpu))
    ingest_s, roi_s, tactile_s, ingest_cpu, roi_cpu = (float(np.median(c)) for c in zip(*runs))
    return {"images": len(manifest), "tactile": len(tactile), "ingest_s": ingest_s, "roi_s": roi_s,
            "tactile_s": tactile_s, "ingest_cpu_s": ingest_cpu, "roi_cpu_s": roi_cpu}


def measure(src: Path, root: Path, layout: str, work: Path, args) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, __file__, "--child", str(root), layout, str(work), "--workers", str(args.workers),
           "--repeats", str(args.repeats), "--tactile-box", args.tactile_box]
    env = {**os.environ, "PYTHONPATH": f"{src}{os.pathsep}{REPO / 'benchmarks'}"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        sys.exit(f"{layout} with {src} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ref", help="a git ref whose src/ is timed too (before)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--tiles", type=int, default=960, help="number of synthetic 256 px tiles")
    parser.add_argument("--tactile-box", default="auto", choices=["auto", "full"])
    parser.add_argument("--rounds", type=int, default=1, help="alternate the sources this many times (median)")
    parser.add_argument("--only", choices=["vt60", "tiles256"], help="time one data set only")
    parser.add_argument("--child", nargs=3, metavar=("ROOT", "LAYOUT", "WORK"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    roi = {"size": 64, "tactile_box": args.tactile_box, "remove_markers": True, "visual_crop": "centre",
           "crop_fraction": 0.5}
    if args.child:
        root, layout, work = args.child
        print(json.dumps(child(Path(root), layout, Path(work), args.workers, args.repeats, roi)))
        return
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        sources = {"working tree": REPO / "src"}
        if args.ref:
            (tmp / "ref").mkdir()
            archive = subprocess.run(["git", "-C", str(REPO), "archive", args.ref, "src"], capture_output=True, check=True)
            subprocess.run(["tar", "-x", "-C", str(tmp / "ref")], input=archive.stdout, check=True)
            sources = {f"{args.ref} (before)": tmp / "ref/src", "working tree (after)": REPO / "src"}
        sys.path.insert(0, str(REPO / "src"))
        from data_throughput import write_vitac_like

        if args.only != "vt60":
            write_vitac_like(tmp / "tiles256", args.tiles)
        if (VT60 / "touch").is_dir() and args.only != "tiles256":
            link_vt60(tmp / "vt60")
        sets = {"vt60 touch, 640x480 grey (real)": (tmp / "vt60", "vt60"),
                f"256 px tiles, half GelSight-like (synthetic)": (tmp / "tiles256", "tiles256")}
        rows, loads, runs = [], [os.getloadavg()[0]], 0
        for name, (root, layout) in sets.items():
            if args.only and layout != args.only:
                continue
            if not root.is_dir():
                print(f"skipped {name}: {VT60} not found", file=sys.stderr)
                continue
            results: dict[str, list[dict]] = {label: [] for label in sources}
            for round_ in range(args.rounds):
                for label, src in sources.items():
                    results[label].append(measure(src, root, layout, tmp / f"work-{layout}-{runs}", args))
                    runs += 1
                    loads.append(os.getloadavg()[0])
                    print(f"{name} / {label} round {round_ + 1} done: {json.dumps(results[label][-1])}", file=sys.stderr)
            for label, measured in results.items():
                rows.append((name, label, {key: float(np.median([m[key] for m in measured])) for key in measured[0]}))
    print(f"ROI settings {json.dumps(roi)}; {args.workers} worker threads on {os.cpu_count()} cores; "
          f"median of {args.repeats} runs after a warm-up, each source and data set in its own process"
          f"{f', median of {args.rounds} alternating rounds' if args.rounds > 1 else ''}; "
          f"load average (1 min) {min(loads):.1f} to {max(loads):.1f} during the run")
    print()
    print("| data | code | images | ingest img/s | ROI img/s | ingest+ROI img/s | ROI img/s, tactile only "
          "| CPU ms/img ingest + ROI | ingest+ROI img/s if that CPU time had the 2 cores to itself |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name, label, r in rows:
        n = int(r["images"])
        cpu = r["ingest_cpu_s"] + r["roi_cpu_s"]
        print(f"| {name} | {label} | {n} | {n / r['ingest_s']:,.0f} | {n / r['roi_s']:,.0f} | "
              f"{n / (r['ingest_s'] + r['roi_s']):,.0f} | {r['tactile'] / r['tactile_s']:,.0f} ({int(r['tactile'])}) | "
              f"{1e3 * r['ingest_cpu_s'] / n:.2f} + {1e3 * r['roi_cpu_s'] / n:.2f} = {1e3 * cpu / n:.2f} | "
              f"{n * min(2, args.workers, os.cpu_count() or 1) / cpu:,.0f} |")


if __name__ == "__main__":
    main()
