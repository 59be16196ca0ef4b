"""Classify stage speed, before vs after: seconds per modality run and images per second.

Runs the classify stage (``run_classify``, params.yaml's ``classify`` section: every setting, seed
and epoch) of one modality with the source tree of a git ref (``--before``, default the commit
before the speed work) and with the working tree, alternately (before, after, after, before, ...)
in fresh subprocesses so that a change in machine load hits both alike; then checks that the two
accuracy tables hold the same numbers. Prints a markdown table.

    python benchmarks/classify_speed.py --root /path/to/a/finished/main/job --repeats 2

``--root`` is the folder the tile paths in ``data/pairs/splits.parquet`` are relative to (the
project root of a run that has finished the pairs stage). With ``--generated`` the generate
stage's folder of that run is used; without it a stand-in is built in a temporary folder: the
target modality's real tiles of the translated pairs (half the training inputs per class, every
test input, as ``generate.train_share: 0.5`` gives) take the place of the generated images, which
keeps the image counts and so the work of the stage, not its accuracies. Nothing is written under
``--root``.

The stage's own images per second (summary.json ``throughput``, printed by the stage) exist only
after the change; the ``all images/s`` column counts, for both, every training image visit
(settings x seeds x epochs) per second of the whole stage run, so it compares like with like.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parents[1]
BEFORE = "5df5da9"  # the commit before the classify speed work

RUNNER = """
import json, sys, time
import yaml
sys.path.insert(0, sys.argv[1])
from vtgen.stages.classify import run_classify
# read, not validated: the stage uses only the classify section and translation.device, and the
# params schema of the 'before' ref may not know keys added since
params = yaml.safe_load(open(sys.argv[2]))
started, cpu = time.perf_counter(), time.process_time()
summary = run_classify(params, sys.argv[3], sys.argv[4], sys.argv[5], sys.argv[6], progress=False)
print("BENCH " + json.dumps({"seconds": time.perf_counter() - started, "cpu_seconds": time.process_time() - cpu,
                             "throughput": summary.get("throughput")}))
"""


def stand_in_generated(root: Path, out: Path) -> Path:
    """generated.parquet per direction whose images are the real target tiles of the translated pairs."""
    for direction in ("v2t", "t2v"):
        pairs = pd.read_parquet(root / "data/pairs" / f"{direction}.parquet")
        train = pairs[pairs["split"] == "train"]
        chosen = pd.concat([train[train["class"] == c].iloc[::2] for c in sorted(train["class"].unique())]
                           + [pairs[pairs["split"] == "test"]]).reset_index(drop=True)
        table = pd.DataFrame({"direction": direction, "scope": "all", "split": chosen["split"], "class": chosen["class"],
                              "input_path": chosen["input_path"], "output_path": chosen["target_path"],
                              "ground_truth_path": chosen["target_path"], "model": "stand-in"})
        (out / direction).mkdir(parents=True, exist_ok=True)
        table.to_parquet(out / direction / "generated.parquet", index=False)
    return out


def source_tree(ref: str, into: Path) -> Path:
    """``src`` of git ``ref`` extracted under ``into``."""
    into.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "src"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


def run_once(src: Path, params: Path, modality: str, root: Path, generated: Path, out: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    done = subprocess.run([sys.executable, "-c", RUNNER, str(src), str(params), modality, "data/pairs", str(generated),
                           str(out)], cwd=root, env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"classify run failed ({src}):\n{done.stderr[-3000:]}")
    line = next(l for l in done.stdout.splitlines() if l.startswith("BENCH "))
    result = json.loads(line[len("BENCH "):])
    result["table"] = pd.read_parquet(out / "accuracy.parquet")
    result["log"] = [l for l in done.stdout.splitlines() if "final test accuracy" in l][-1]
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", required=True, help="project root of a run that has finished the pairs stage")
    parser.add_argument("--generated", help="that run's generate folder (default: a stand-in, see the docstring)")
    parser.add_argument("--modality", default="tactile", choices=["visual", "tactile"])
    parser.add_argument("--params", default=str(REPO / "params.yaml"))
    parser.add_argument("--before", default=BEFORE, help=f"git ref of the 'before' code (default {BEFORE})")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    root = Path(args.root).resolve()
    with tempfile.TemporaryDirectory(prefix="classify_speed_") as tmp:
        tmp = Path(tmp)
        generated = Path(args.generated).resolve() if args.generated else stand_in_generated(root, tmp / "generated")
        versions = {f"before ({args.before})": source_tree(args.before, tmp / "before"), "after (working tree)": REPO / "src"}
        results: dict[str, list[dict]] = {name: [] for name in versions}
        load = [os.getloadavg()[0]]
        for repeat in range(args.repeats):  # ABBA: before first in even repeats, after first in odd ones
            for name, src in list(versions.items())[::1 if repeat % 2 == 0 else -1]:
                result = run_once(src, Path(args.params).resolve(), args.modality, root, generated,
                                  tmp / f"out_{len(results[name])}_{name.split()[0]}")
                results[name].append(result)
                load.append(os.getloadavg()[0])
                print(f"# {name}, run {repeat + 1}: {result['seconds']:.1f} s; {result['log']}", file=sys.stderr)
        reference = results[next(iter(versions))][0]["table"]
        visits = int((reference.groupby(["setting", "seed"])["train_images"].first()
                      * reference["epoch"].max()).sum())
        command = (f"python benchmarks/classify_speed.py --root {args.root}"
                   + (f" --generated {args.generated}" if args.generated else "")
                   + (f" --params {args.params}" if Path(args.params).resolve() != REPO / "params.yaml" else "")
                   + f" --modality {args.modality} --repeats {args.repeats}")
        print(f"classify {args.modality}: {visits} training image visits per run "
              f"({'stand-in' if not args.generated else 'generated'} images), torch threads: classify.threads; "
              f"load average (1 min) seen {min(load):.1f} to {max(load):.1f}; `{command}`\n")
        print("| code | stage wall s per run (each run) | stage CPU s (each run) | all images/s (wall) | "
              "training images/s | evaluation images/s | accuracies identical to before |")
        print("|---|---|---|---|---|---|---|")
        for name, runs in results.items():
            seconds, cpu = [r["seconds"] for r in runs], [r["cpu_seconds"] for r in runs]
            speeds = [r["throughput"] for r in runs if r["throughput"]]
            same = all(r["table"][["test_accuracy", "gan_test_accuracy"]].equals(
                reference[["test_accuracy", "gan_test_accuracy"]]) for r in runs)
            own = (f"{max(s['train_images_per_second'] for s in speeds):.0f} | "
                   f"{max(s['eval_images_per_second'] for s in speeds):.0f}") if speeds else "- | -"
            print(f"| {name} | {min(seconds):.1f} ({', '.join(f'{v:.1f}' for v in seconds)}) | "
                  f"{min(cpu):.1f} ({', '.join(f'{v:.1f}' for v in cpu)}) | {visits / min(seconds):.0f} | {own} | "
                  f"{'yes' if same else 'NO'} |")
        before, after = results.values()
        pairs = list(zip(before, after))  # runs of one repeat: next to each other in time
        print(f"\nspeed-up, before / after: wall {min(r['seconds'] for r in before) / min(r['seconds'] for r in after):.2f}x "
              f"(best runs), CPU {min(r['cpu_seconds'] for r in before) / min(r['cpu_seconds'] for r in after):.2f}x; "
              f"per interleaved pair (wall / CPU): "
              + ", ".join(f"{b['seconds'] / a['seconds']:.2f}x / {b['cpu_seconds'] / a['cpu_seconds']:.2f}x" for b, a in pairs))

if __name__ == "__main__":
    main()
