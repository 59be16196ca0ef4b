"""The whole main job at 1x, 4x and 10x the images of a real dataset: seconds and peak memory per stage, and the slope.

Builds a real-like dataset per scale from ``../shared/data/vt60_subset`` (480 touch frames of 640x480
grey, 240 photos of 300x300 RGB, 10 classes, 2 instances each) in its own layout
(``<modality>/<class>/<instance>/<name>.jpg``, read with ``source: pattern``): at scale s every
instance gives s instances, copy 0 the original files, copies 1.. each frame cropped to a random
90-100% of each side at a random place, resized back to the frame's size, mirrored left-right with
probability 1/2 and its brightness scaled by a factor in [0.8, 1.2] (one crop, mirror and factor per
copy and frame), written as JPEG at quality 95. So s = 10 gives 7,200 images of 20 x s instances.

Each scale runs the main job (``snakemake --cores 2``) in its own fresh clone of the project's
committed HEAD, with default params except the dataset lines (``source: pattern``, the pattern,
``roi.tactile_box: auto``; the settings vt60_subset needs, as in README's "your own data"), and the
code of that clone (``PYTHONPATH``). It then reads the stages' own ``timing.json`` (wall seconds, peak
RSS of the stage process and of its worker processes) and prints one markdown table: per stage the
seconds at each scale, the least-squares slope in seconds per 1,000 images, and the largest peak RSS.
Where a stage runs once per direction or modality, its jobs' seconds are summed (they run side by
side with ``--cores 2``, so the sum is the work, not the wall they added), with the longest job in
brackets, and the wall of the whole job is printed apart.

    python benchmarks/main_job_scaling.py --scales 1 4 10 --work /tmp/main_scaling
    python benchmarks/main_job_scaling.py --scales 1 --work /tmp/main_scaling   # one scale (reuses its data)
    python benchmarks/main_job_scaling.py --scales 1 4 10 --work /tmp/main_scaling --table-only
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared" / "data" / "vt60_subset"
PATTERN = "{modality}/{class}/{instance}/{name}.jpg"
STAGE_ORDER = ["ingest", "roi", "pairs", "train", "generate", "classify", "score", "report"]


def _copy_frame(job: tuple[str, str, int]) -> None:
    """Write one augmented copy (``job`` = source path, target path, seed) of a frame."""
    from PIL import Image, ImageEnhance

    source, target, seed = job
    rng = np.random.default_rng(seed)
    with Image.open(source) as frame:
        mode, (w, h) = frame.mode, frame.size
        cw, ch = int(w * rng.uniform(0.9, 1.0)), int(h * rng.uniform(0.9, 1.0))
        x, y = int(rng.integers(0, w - cw + 1)), int(rng.integers(0, h - ch + 1))
        image = frame.crop((x, y, x + cw, y + ch)).resize((w, h), Image.Resampling.BILINEAR)
    if rng.random() < 0.5:
        image = image.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
    image = ImageEnhance.Brightness(image).enhance(float(rng.uniform(0.8, 1.2)))
    image.convert(mode).save(target, quality=95)


def build_dataset(root: Path, scale: int) -> int:
    """The scale's dataset under ``root`` (kept when complete); returns its number of images."""
    done = root / ".complete"
    if done.exists():
        return int(done.read_text())
    if root.exists():
        shutil.rmtree(root)
    jobs, count = [], 0
    for path in sorted(SOURCE.glob("*/*/*/*.jpg")):
        modality, name, instance = path.parts[-4], path.parts[-3], path.parts[-2]
        for copy in range(scale):
            folder = root / modality / name / (instance if copy == 0 else f"{instance}c{copy}")
            folder.mkdir(parents=True, exist_ok=True)
            target = folder / path.name
            if copy == 0:
                shutil.copyfile(path, target)
            else:
                jobs.append((str(path), str(target), zlib.crc32(f"{path.name}:{copy}".encode())))
            count += 1
    with ProcessPoolExecutor(max_workers=2) as pool:
        list(pool.map(_copy_frame, jobs, chunksize=64))
    done.write_text(str(count))
    return count


def _set_dataset(params: Path, data: Path) -> None:
    """Point the clone's params.yaml at ``data`` (pattern layout, round-sensor ROI); nothing else changes."""
    import yaml

    text = params.read_text()
    settings = yaml.safe_load(text)
    replacements = {f"source: {settings['dataset']['source']}": "source: pattern",
                    f"path: {settings['dataset']['path']}": f"path: {data}",
                    f"tactile_box: {settings['roi']['tactile_box']}": "tactile_box: auto"}
    for old, new in replacements.items():
        if old not in text:
            sys.exit(f"{params}: cannot find '{old}' to replace")
        text = text.replace(old, new, 1)
    text = text.replace("source: pattern", f"source: pattern\n  pattern: \"{PATTERN}\"", 1)
    params.write_text(text)
    check = yaml.safe_load(params.read_text())["dataset"]
    assert check["source"] == "pattern" and check["pattern"] == PATTERN, check


def run_scale(work: Path, scale: int) -> dict:
    """Build the data, clone, run the main job; returns the stages' timing records and the job's wall."""
    images = build_dataset(work / f"data_x{scale}", scale)
    clone = work / f"clone_x{scale}"
    if clone.exists():
        shutil.rmtree(clone)
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    _set_dataset(clone / "params.yaml", work / f"data_x{scale}")
    env = {**os.environ, "PYTHONPATH": str(clone / "src")}
    log = work / f"main_x{scale}.log"
    started = time.perf_counter()
    with log.open("w") as out:
        result = subprocess.run(["snakemake", "--cores", "2"], cwd=clone, env=env, stdout=out, stderr=subprocess.STDOUT)
    wall = time.perf_counter() - started
    if result.returncode:
        sys.exit(f"main job at {scale}x failed (rc {result.returncode}); see {log}")
    return {"scale": scale, "images": images, "wall": wall, "stages": stage_records(clone),
            "commit": subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True,
                                     text=True).stdout.strip()}


def stage_records(clone: Path) -> dict:
    """{stage: seconds summed over its jobs, the longest job's seconds, jobs, largest peak RSS} from a run's timing.json."""
    stages: dict = {}
    for path in sorted(clone.glob("**/timing.json")):
        record = json.loads(path.read_text())
        stage = record.get("stage") or path.parent.name
        entry = stages.setdefault(stage, {"seconds": 0.0, "longest": 0.0, "jobs": 0, "peak_rss_mb": 0.0,
                                          "peak_rss_children_mb": 0.0})
        entry["seconds"] += float(record["seconds"])
        entry["longest"] = max(entry["longest"], float(record["seconds"]))
        entry["jobs"] += 1
        for key in ("peak_rss_mb", "peak_rss_children_mb"):
            entry[key] = max(entry[key], float(record.get(key) or 0.0))
    return stages


def slope(images: list[int], seconds: list[float]) -> float:
    """Least-squares seconds per 1,000 images."""
    if len(images) < 2:
        return float("nan")
    return float(np.polyfit(np.asarray(images) / 1000.0, np.asarray(seconds), 1)[0])


def table(results: list[dict]) -> str:
    header = " | ".join(f"{r['scale']}x: {r['images']:,} images" for r in results)
    lines = [f"| stage (jobs) | {header} | slope, s per 1,000 images (summed) | peak RSS MB (stage / workers) |",
             "|---|" + "---|" * len(results) + "---|---|"]
    names = [s for s in STAGE_ORDER if any(s in r["stages"] for r in results)]
    names += sorted({s for r in results for s in r["stages"]} - set(names))
    for name in names:
        cells = [r["stages"].get(name) for r in results]
        seconds = [c["seconds"] if c else float("nan") for c in cells]
        jobs = max(c["jobs"] for c in cells if c)
        rss = max(c["peak_rss_mb"] for c in cells if c)
        rss_children = max(c["peak_rss_children_mb"] for c in cells if c)
        longest = [c["longest"] if c else float("nan") for c in cells]
        lines.append(f"| {name} ({jobs}) | " + " | ".join(
            f"{s:.1f} s" if jobs == 1 else f"{s:.1f} s ({w:.1f})" for s, w in zip(seconds, longest))
                     + f" | {slope([r['images'] for r in results], seconds):.1f} | {rss:.0f} / {rss_children:.0f} |")
    walls = [r["wall"] for r in results]
    lines.append("| **main job, wall** | " + " | ".join(f"**{w:.0f} s ({w / 60:.1f} min)**" for w in walls)
                 + f" | {slope([r['images'] for r in results], walls):.1f} | |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", type=int, nargs="+", default=[1, 4, 10])
    parser.add_argument("--work", type=Path, required=True, help="folder for the datasets, clones and logs (kept)")
    parser.add_argument("--table-only", action="store_true", help="print the table of finished runs under --work")
    args = parser.parse_args()
    if not SOURCE.exists():
        sys.exit(f"{SOURCE} not found: this benchmark builds its data from vt60_subset")
    args.work.mkdir(parents=True, exist_ok=True)
    results = []
    for scale in args.scales:
        if args.table_only:
            result = json.loads((args.work / f"result_x{scale}.json").read_text())
            result["stages"] = stage_records(args.work / f"clone_x{scale}")
            results.append(result)
            continue
        result = run_scale(args.work, scale)
        (args.work / f"result_x{scale}.json").write_text(json.dumps(result, indent=1) + "\n")
        print(f"{scale}x: {result['images']} images, {result['wall']:.0f} s", flush=True)
        results.append(result)
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.machine()) if Path("/proc/cpuinfo").exists() else platform.machine()
    print(f"\ncommit {results[0]['commit']}, {os.cpu_count()} cores ({cpu}), python {platform.python_version()}\n")
    print(table(results))


if __name__ == "__main__":
    main()
