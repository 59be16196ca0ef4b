"""Border bands and corner washes in a finished run's generated test images, counted per direction.

An image is an *edge outlier* when the largest gap between the mean colour of one of its edge strips and
that of its interior (:func:`unaligned_ablation.edge_gap`, 4 px strips at the model's size) is above the 99th
percentile of the real training images of the target modality, so about 1% of real images are. Prints, per
direction, the share among the generated test images and among the real test targets (95% Wilson intervals).

    python benchmarks/edge_outliers.py --run /tmp/s12/synnc --run /tmp/s12/vt60
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from unaligned_ablation import edge_gap  # benchmarks/ is on sys.path
from vtgen.core.classifier import wilson_interval
from vtgen.core.domain import DIRECTIONS
from vtgen.io.images import read_tiles
from vtgen.io.params import model_settings


def shares(run: Path) -> list[str]:
    """One markdown row per direction of ``run`` that has generated test images."""
    params = yaml.safe_load((run / "params.yaml").read_text())  # read, not validated: older runs lack newer keys
    size = model_settings(params)["size"]
    splits = pd.read_parquet(run / "data" / "pairs" / "splits.parquet")
    rows = []
    for direction, (_, target) in DIRECTIONS.items():
        table = run / "data" / "generated" / direction / "generated.parquet"
        if not table.is_file():
            continue
        generated = pd.read_parquet(table)
        generated = generated[generated["split"] == "test"]
        real = splits[splits["modality"] == target]
        threshold = np.quantile(edge_gap(read_tiles(list(real[real["split"] == "train"]["path"]), size, run)), 0.99)
        cells = []
        for paths in (list(generated["output_path"]), list(real[real["split"] == "test"]["path"])):
            share = float((edge_gap(read_tiles(paths, size, run)) > threshold).mean())
            low, high = wilson_interval(share, len(paths))
            cells.append(f"{share:.3f} [{low:.3f}, {high:.3f}], n {len(paths)}")
        rows.append(f"| {run} | {direction} | {cells[0]} | {cells[1]} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, type=Path, help="a finished run folder (repeatable)")
    args = parser.parse_args()
    print("| run | direction | edge outliers, generated test [95%] | real test targets [95%] |\n|---|---|---|---|")
    for run in args.run:
        print("\n".join(shares(run.resolve())), flush=True)


if __name__ == "__main__":
    main()
