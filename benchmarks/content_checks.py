"""Cost of vtgen's content records (issue 25): hashing a dataset folder cold and warm, and the start-of-run
check (``vtgen.pipeline.reconcile``) and ``dvc commit`` on a finished project.

    python benchmarks/content_checks.py --images 7000 --source ../shared/data/vt60_subset
    python benchmarks/content_checks.py --project /path/to/finished/project   # reconcile, cold and warm

``--images N`` copies the image files of ``--source`` (round robin, each copy one byte different, so that
every file is distinct) into a temporary folder until there are N, then times ``Hasher.hash`` of the folder
with no stat cache (every file read: the first run after a change) and with it (every later run: stat only).
Prints a markdown table; seconds are wall time on this machine, so read them beside its load.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from vtgen.io.contents import CACHE, Hasher


def timed(func, repeats: int) -> list[float]:
    seconds = []
    for _ in range(repeats):
        started = time.perf_counter()
        func()
        seconds.append(time.perf_counter() - started)
    return seconds


def dataset(source: Path, count: int, where: Path) -> tuple[int, int]:
    files = sorted(p for p in source.rglob("*") if p.suffix.lower() in (".jpg", ".jpeg", ".png"))
    total = 0
    for i in range(count):
        src = files[i % len(files)]
        target = where / f"copy_{i // len(files)}" / src.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        data = bytearray(src.read_bytes())
        data[-1] ^= i // len(files) & 0xFF  # distinct bytes per copy
        target.write_bytes(bytes(data))
        total += len(data)
    return count, total


def hash_folder(folder: Path, repeats: int) -> list[tuple[str, list[float]]]:
    root = folder.parent

    def cold() -> None:
        (root / CACHE).unlink(missing_ok=True)
        hasher = Hasher(root)
        hasher.hash(folder)
        hasher.save()

    cold_seconds = timed(cold, repeats)
    warm_seconds = timed(lambda: Hasher(root).hash(folder), repeats)
    return [("hash, no stat cache (every file read)", cold_seconds), ("hash, stat cache (stat only)", warm_seconds)]


def reconcile_project(project: Path, repeats: int) -> list[tuple[str, list[float]]]:
    import yaml

    from vtgen.pipeline import reconcile

    params = yaml.safe_load((project / "params.yaml").read_text())
    cache = project / CACHE
    saved = cache.read_bytes() if cache.exists() else None

    def cold() -> None:
        cache.unlink(missing_ok=True)
        reconcile(params, project)

    rows = [("reconcile, no stat cache", timed(cold, repeats)),
            ("reconcile, stat cache", timed(lambda: reconcile(params, project), repeats))]
    if saved is not None:
        cache.write_bytes(saved)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", type=int, default=0)
    parser.add_argument("--source", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/vt60_subset")
    parser.add_argument("--project", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    rows = []
    if args.images:
        with tempfile.TemporaryDirectory() as tmp:
            folder = Path(tmp) / "dataset"
            count, size = dataset(args.source, args.images, folder)
            print(f"dataset: {count} files, {size / 1e6:.0f} MB (copies of {args.source})")
            rows += hash_folder(folder, args.repeats)
    if args.project:
        files = sum(1 for _ in args.project.rglob("*") if _.is_file())
        print(f"project: {args.project} ({files} files)")
        rows += reconcile_project(args.project, args.repeats)
    print("| check | median s | min-max s | n |\n|---|---|---|---|")
    for name, seconds in rows:
        print(f"| {name} | {statistics.median(seconds):.2f} | {min(seconds):.2f}-{max(seconds):.2f} | {len(seconds)} |")
    print(f"(load average {os.getloadavg()[0]:.1f} at the end)")


if __name__ == "__main__":
    main()
