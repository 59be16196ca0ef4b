"""Test accuracy of the classify stage's network by training length, on a finished run's real tiles.

Trains ``AlexNet`` with the run's ``classify`` settings (size, width, batch size, learning rate) on the real
training tiles of one modality for each number of epochs and seed, and prints its test accuracy after the
last epoch with the 95% Wilson interval, and its test accuracy at every tenth of the run. This is the
network ``conditioning: inferred`` uses to read the class from a generator's input
(``translation.inferred_epochs`` sets its length) and the classify stage's real-only classifier (the
paper's 10 epochs).

    python benchmarks/classifier_epochs.py --run /path/to/run --modality tactile --epochs 10 30 60 --seeds 0 1
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd
import torch
import yaml

from vtgen.core.classifier import train_classifier, wilson_interval
from vtgen.io.images import read_tiles


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, required=True, help="a run folder with params.yaml and data/pairs")
    parser.add_argument("--modality", choices=["visual", "tactile"], required=True)
    parser.add_argument("--epochs", type=int, nargs="+", default=[10, 30, 60])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    args = parser.parse_args()
    cfg = yaml.safe_load((args.run / "params.yaml").read_text())["classify"]
    splits = pd.read_parquet(args.run / "data/pairs/splits.parquet")
    classes = sorted(set(splits["class"]))
    index = {c: i for i, c in enumerate(classes)}

    def load(split: str) -> tuple[torch.Tensor, torch.Tensor]:
        rows = splits[(splits["split"] == split) & (splits["modality"] == args.modality)].sort_values("path")
        return read_tiles(list(rows["path"]), cfg["size"], args.run), torch.tensor([index[c] for c in rows["class"]])

    (train_x, train_y), (test_x, test_y) = load("train"), load("test")
    print(f"{args.run} {args.modality}: {len(train_y)} training and {len(test_y)} test tiles, {len(classes)} classes")
    print("| epochs | seed | test accuracy [95%] | test accuracy at each tenth of the run |")
    print("|---|---|---|---|")
    for epochs in args.epochs:
        for seed in args.seeds:
            settings = {k: cfg[k] for k in ("size", "width", "batch_size", "lr")} | {"epochs": epochs}
            run = train_classifier(train_x, train_y, test_x, test_y, len(classes), settings, seed)
            final = run.test_accuracy[-1]
            low, high = wilson_interval(final, len(test_y))
            curve = ", ".join(f"{a:.2f}" for a in run.test_accuracy[max(1, epochs // 10) - 1::max(1, epochs // 10)])
            print(f"| {epochs} | {seed} | {final:.3f} [{low:.3f}, {high:.3f}] | {curve} |", flush=True)


if __name__ == "__main__":
    main()
