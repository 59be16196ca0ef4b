"""One markdown row per finished run folder, for comparing main jobs side by side in one direction.

Reads each run's ``data/scores/summary.json`` (the score stage's goal numbers, each with a 95% interval and
n), ``reports/metrics.json`` (the classify stage: GAN-test, real-only and real+generated accuracies with the
paired 95% interval of the gain), ``models/<direction>/all/train.json`` (the snapshot the referee kept) and
``models/<direction>/all/timing.json`` (training seconds). Prints nothing it did not read; a value a run
lacks prints as "-".

    python benchmarks/main_job_table.py --direction t2v "old=/tmp/run_a" "new=/tmp/run_b"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from unaligned_goals import MODALITY


def interval(entry: dict | None) -> str:
    """``value [low, high]`` to three significant figures, or "-"."""
    if not entry:
        return "-"
    return f"{entry['value']:.3g} [{entry['low']:.3g}, {entry['high']:.3g}]"


def gain(metrics: dict, setting: str, real: str) -> str:
    """``real → with generated (gain [paired 95%])`` for one classify setting."""
    paired = metrics["gain_from_generated_paired95"][setting]
    return (f"{metrics[real]:.3f} → {metrics[setting]:.3f} ({metrics['gain_from_generated'][setting]:+.3f} "
            f"[{paired['low']:+.3f}, {paired['high']:+.3f}])")


def row(name: str, run: Path, direction: str) -> str:
    goals = json.loads((run / "data/scores/summary.json").read_text())["goals"][direction]
    metrics = json.loads((run / "reports/metrics.json").read_text())["classify"][MODALITY[direction][1]]
    model = run / "models" / direction / "all"
    train = json.loads((model / "train.json").read_text())
    timing = json.loads((model / "timing.json").read_text())
    fid = goals["fid_classifier"]
    cells = [name, interval(goals["coverage_classifier"]["generated"]),
             f"{goals['diversity_pixels']['value']:.2f} / {goals['diversity_classifier']['value']:.2f}",
             interval(fid["generated"]), interval(goals["kid_classifier"]["generated"]),
             interval(fid.get("generated_minus", {}).get("mean_image")),
             interval(goals["memorisation_classifier"]["generated"]), f"{metrics['gan_test']:.3f}",
             gain(metrics, "low-data real+generated", "low-data real"), gain(metrics, "real+generated", "real"),
             str(train.get("selection", {}).get("step", "-")), f"{timing['wall_seconds']:.0f}"]
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--direction", choices=sorted(MODALITY), required=True)
    parser.add_argument("runs", nargs="+", help="name=run folder")
    args = parser.parse_args()
    header = ["run", "coverage [95%]", "diversity px / feat", "FID (classifier) [95%]", "KID (classifier) [95%]",
              "paired FID minus mean image [95%]", "memorisation [95%]", "GAN-test",
              "low-data real → +generated (gain [95%])", "all real → +generated (gain [95%])", "step kept", "train s"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for spec in args.runs:
        name, _, folder = spec.partition("=")
        print(row(name, Path(folder), args.direction))


if __name__ == "__main__":
    main()
