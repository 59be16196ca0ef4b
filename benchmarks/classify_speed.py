"""Classify stage speed and accuracy, before vs after: seconds per modality run, images per second, accuracies.

Runs the classify stage (``run_classify``, params.yaml's ``classify`` section: every setting, seed
and epoch) of one modality with the source tree of a git ref (``--before``) and with the working
tree, once per ``--variant`` of the params (dotted overrides, e.g. ``patience2:classify.patience=2``),
each in a fresh subprocess: alternately (before, after..., then the reverse order in the next
repeat) so that a change in machine load hits all alike, or with ``--side-by-side`` all at once. Prints a markdown table: wall and CPU seconds, images
per second, epochs run, and the final test accuracy of ``real`` and of the policy's choice (mean
over seeds, 95% Wilson interval on the n real test images, the spread over seeds).

    python benchmarks/classify_speed.py --root /path/to/a/run --modality visual --variant patience2:classify.patience=2

``--root`` is the folder the tile paths in the split table are relative to; ``--pairs`` (default
``data/pairs``, relative to it) holds ``splits.parquet``. With ``--generated`` that generate
folder is used; without it a stand-in is built in a temporary folder from the split table alone:
per class, every second real training tile of the target modality is a "generated" training image
(its input a training tile of the other modality of the class, taken in turn) and every real test
tile a "generated" test image, as ``generate.train_share: 0.5`` gives. That keeps the image counts
and so the work of the stage, not its accuracies (the stand-ins are real images). Nothing is
written under ``--root``.
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
import yaml

REPO = Path(__file__).resolve().parents[1]
BEFORE = "f928692"  # the commit before the classify policy, validation split and early stopping
DIRECTIONS = {"v2t": ("visual", "tactile"), "t2v": ("tactile", "visual")}

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
                             "summary": summary}))
"""


def stand_in_generated(splits: pd.DataFrame, out: Path) -> Path:
    """generated.parquet per direction whose images are real target tiles (see the module docstring)."""
    for direction, (source, target) in DIRECTIONS.items():
        rows = []
        for split, step in (("train", 2), ("test", 1)):
            for cls in sorted(splits["class"].unique()):
                inputs = list(splits[(splits["modality"] == source) & (splits["split"] == split)
                                     & (splits["class"] == cls)].sort_values("path")["path"])
                targets = splits[(splits["modality"] == target) & (splits["split"] == split)
                                 & (splits["class"] == cls)].sort_values("path")["path"].iloc[::step]
                rows += [{"direction": direction, "scope": "all", "split": split, "class": cls,
                          "input_path": inputs[i % len(inputs)], "output_path": path, "ground_truth_path": None,
                          "model": "stand-in"} for i, path in enumerate(targets) if inputs]
        (out / direction).mkdir(parents=True, exist_ok=True)
        pd.DataFrame(rows).to_parquet(out / direction / "generated.parquet", index=False)
    return out


def source_tree(ref: str, into: Path) -> Path:
    """``src`` of git ``ref`` extracted under ``into``."""
    into.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "src"], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into / "src"


def with_overrides(params: dict, overrides: list[str]) -> dict:
    """``params`` with ``dotted.key=value`` overrides (values read as YAML)."""
    params = json.loads(json.dumps(params))
    for item in overrides:
        key, _, value = item.partition("=")
        *parents, last = key.split(".")
        node = params
        for name in parents:
            node = node[name]
        node[last] = yaml.safe_load(value)
    return params


def start(src: Path, params: Path, modality: str, root: Path, pairs: str, generated: Path, out: Path,
          logs: Path) -> subprocess.Popen:
    """One classify run in a fresh process (its output in ``logs``.out/.err)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    return subprocess.Popen([sys.executable, "-c", RUNNER, str(src), str(params), modality, pairs, str(generated),
                             str(out)], cwd=root, env=env, stdout=open(f"{logs}.out", "w"),
                            stderr=open(f"{logs}.err", "w"))


def finish(process: subprocess.Popen, out: Path, logs: Path) -> dict:
    if process.wait():
        raise SystemExit(f"classify run failed:\n{Path(f'{logs}.err').read_text()[-3000:]}")
    line = next(l for l in Path(f"{logs}.out").read_text().splitlines() if l.startswith("BENCH "))
    result = json.loads(line[len("BENCH "):])
    result["table"] = pd.read_parquet(out / "accuracy.parquet")
    return result


def accuracy_cell(stats: dict | None) -> str:
    if not stats or stats.get("final_mean") is None:
        return "-"
    low, high = stats.get("interval") or (float("nan"), float("nan"))
    return f"{stats['final_mean']:.3f} ± {stats.get('final_std') or 0:.3f} [{low:.3f}, {high:.3f}]"


def policy_cell(summary: dict) -> str:
    policy = summary.get("policy")
    if not policy:
        return "- (no policy)"
    test = policy["test"]
    low, high = test.get("interval") or (float("nan"), float("nan"))
    return f"{policy['chosen']}: {test['accuracy']:.3f} [{low:.3f}, {high:.3f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--root", required=True, help="folder the split table's tile paths are relative to")
    parser.add_argument("--pairs", default="data/pairs", help="folder of splits.parquet, relative to --root")
    parser.add_argument("--generated", help="a generate folder (default: a stand-in, see the docstring)")
    parser.add_argument("--modality", default="tactile", choices=["visual", "tactile"])
    parser.add_argument("--params", default=str(REPO / "params.yaml"))
    parser.add_argument("--before", default=BEFORE, help=f"git ref of the 'before' code (default {BEFORE})")
    parser.add_argument("--variant", action="append", default=[],
                        help="NAME:key=value[,key=value]: one more 'after' run with these params overrides")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--side-by-side", action="store_true",
                        help="start every code's run of a repeat at once (one process each): on a shared, loaded "
                             "machine they then meet the same load; CPU seconds stay comparable, wall seconds inflate")
    args = parser.parse_args()
    root = Path(args.root).resolve()
    base = yaml.safe_load(Path(args.params).read_text())
    with tempfile.TemporaryDirectory(prefix="classify_speed_") as tmp:
        tmp = Path(tmp)
        splits = pd.read_parquet(root / args.pairs / "splits.parquet")
        generated = Path(args.generated).resolve() if args.generated else stand_in_generated(splits, tmp / "generated")
        codes = {f"before ({args.before})": (source_tree(args.before, tmp / "before"), [])}
        codes["after (working tree)"] = (REPO / "src", [])
        for item in args.variant:
            name, _, overrides = item.partition(":")
            codes[f"after, {name}"] = (REPO / "src", overrides.split(","))
        params_files = {}
        for name, (_, overrides) in codes.items():
            params_files[name] = tmp / f"params_{len(params_files)}.yaml"
            params_files[name].write_text(yaml.safe_dump(with_overrides(base, overrides)))
        results: dict[str, list[dict]] = {name: [] for name in codes}
        load = [os.getloadavg()[0]]
        for repeat in range(args.repeats):  # before first in even repeats, last in odd ones
            order = list(codes.items())[::1 if repeat % 2 == 0 else -1]
            batches = [order] if args.side_by_side else [[item] for item in order]
            for batch in batches:
                running = []
                for name, (src, _) in batch:
                    out, logs = tmp / f"out_{repeat}_{list(codes).index(name)}", tmp / f"log_{repeat}_{list(codes).index(name)}"
                    running.append((name, out, logs, start(src, params_files[name], args.modality, root, args.pairs,
                                                           generated, out, logs)))
                for name, out, logs, process in running:
                    result = finish(process, out, logs)
                    results[name].append(result)
                    load.append(os.getloadavg()[0])
                    print(f"# {name}, run {repeat + 1}: {result['seconds']:.1f} s wall, {result['cpu_seconds']:.1f} s CPU",
                          file=sys.stderr, flush=True)
        counts = results[next(iter(codes))][0]["summary"]["counts"]
        command = (f"python benchmarks/classify_speed.py --root {args.root} --pairs {args.pairs}"
                   + (f" --generated {args.generated}" if args.generated else "")
                   + f" --modality {args.modality} --repeats {args.repeats}"
                   + (" --side-by-side" if args.side_by_side else "")
                   + "".join(f" --variant {v}" for v in args.variant))
        print(f"classify {args.modality}: {counts['real_train']} real training, {counts.get('real_val', '?')} "
              f"validation, {counts['real_test']} test images, {counts['generated_train']} "
              f"{'stand-in' if not args.generated else 'generated'} training images; seeds "
              f"{base['classify']['seeds']}, {base['classify']['epochs']} epochs at most; torch threads "
              f"{base['classify']['threads']}; load average (1 min) seen {min(load):.1f} to {max(load):.1f}; "
              f"`{command}`\n")
        print("| code | stage wall s (each run) | stage CPU s (each run) | training image visits | training images/s "
              "| evaluation images/s | epochs run (mean) | real: test accuracy ± std over seeds [95%] | "
              "policy: chosen, test accuracy [95%] |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name, runs in results.items():
            seconds, cpu = [r["seconds"] for r in runs], [r["cpu_seconds"] for r in runs]
            summary, table = runs[0]["summary"], runs[0]["table"]
            speed = summary.get("throughput") or {}
            last = table.groupby(["setting", "seed"])["epoch"].max()
            print(f"| {name} | {min(seconds):.1f} ({', '.join(f'{v:.1f}' for v in seconds)}) | "
                  f"{min(cpu):.1f} ({', '.join(f'{v:.1f}' for v in cpu)}) | {speed.get('train_images', '-')} | "
                  f"{speed.get('train_images_per_second') or '-'} | {speed.get('eval_images_per_second') or '-'} | "
                  f"{last.mean():.1f} | {accuracy_cell(summary['settings'].get('real'))} | {policy_cell(summary)} |")
        print("\nall settings (test accuracy, mean ± std over seeds [95% Wilson on the n test images]):")
        for name, runs in results.items():
            settings = runs[0]["summary"]["settings"]
            print(f"- {name}: " + "; ".join(f"{s} {accuracy_cell(v)}" for s, v in settings.items()))


if __name__ == "__main__":
    main()
