"""Do the extra crops of `class_gan.views` look like the centre tiles the test uses?

For the training frames of a finished run (its params.yaml, data/roi and data/pairs), per modality: the mean grey
level of the centre tiles and of ``--crops`` random crops per frame (the crops `vtgen train` adds), and the median
and 90th percentile of the ablation's edge gap (largest distance between an edge strip's mean colour and the
interior's, RGB 0-255).

    python benchmarks/frame_view_shading.py <run folder> [--crops 7]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from unaligned_ablation import edge_gap  # benchmarks/ is on sys.path
from vtgen.io.images import read_tiles
from vtgen.stages.train import frame_views


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a run folder holding params.yaml, data/roi and data/pairs")
    parser.add_argument("--crops", type=int, default=7, help="random crops per frame (class_gan.views - 1)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    run = args.run.resolve()
    params = yaml.safe_load((run / "params.yaml").read_text())
    splits = pd.read_parquet(run / "data" / "pairs" / "splits.parquet")
    tiles = pd.read_parquet(run / "data" / "roi" / "tiles.parquet")
    size = params["roi"]["size"]
    print(f"# {run}: centre tiles vs {args.crops} random crops per training frame ({size} px)")
    print("| modality | tiles / crops | mean grey, tiles (sd) | mean grey, crops (sd) | edge gap median, tiles / crops | "
          "edge gap 90th percentile, tiles / crops |")
    print("|---|---|---|---|---|---|")
    for modality in ("tactile", "visual"):
        paths = list(splits[(splits["split"] == "train") & (splits["modality"] == modality)]["path"])
        centre = read_tiles(paths, size, run)
        crops = frame_views(paths, tiles, Path("data/roi/tiles"), params["roi"], args.crops, size,
                            params["translation"]["seed"], run)
        grey = [x.float().mean(dim=(1, 2, 3)).numpy() for x in (centre, crops)]
        gaps = [edge_gap(x) for x in (centre, crops)]
        print(f"| {modality} | {len(centre)} / {len(crops)} | {grey[0].mean():.1f} ({grey[0].std():.1f}) | "
              f"{grey[1].mean():.1f} ({grey[1].std():.1f}) | {np.median(gaps[0]):.1f} / {np.median(gaps[1]):.1f} | "
              f"{np.percentile(gaps[0], 90):.1f} / {np.percentile(gaps[1], 90):.1f} |")


if __name__ == "__main__":
    main()
