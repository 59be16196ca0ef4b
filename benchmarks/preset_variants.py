"""Train one direction with preset overrides and print test L1 and texture energy: a quick variant check.

Reads the pair tables of a finished main job (``data/pairs``). Each variant is one training run
through ``train_translator`` with the selected preset, the JSON overrides applied on top.
Texture energy is the mean absolute 3x3 Laplacian of an image; the ratio of generated to real
says whether outputs keep the fine texture (1.0) or are blurred (below 1). Test L1 means something
only where the test pairs are aligned views (the SYNTHETIC default).

    python benchmarks/preset_variants.py --variant '{"noise": true}' --variant '{"noise": false}'
"""

from __future__ import annotations

import argparse
import json

import pandas as pd
import torch
import torch.nn.functional as F

from vtgen.io.params import load_params, model_settings
from vtgen.core.gan import to_model_range
from vtgen.stages.train import load_pair_data, train_translator


def texture_energy(images: torch.Tensor) -> torch.Tensor:
    """Mean |Laplacian| per image of an N x 3 x S x S batch (4-neighbour kernel, valid convolution)."""
    kernel = torch.tensor([[0.0, -1, 0], [-1, 4, -1], [0, -1, 0]]).view(1, 1, 3, 3).repeat(3, 1, 1, 1)
    return F.conv2d(images, kernel, groups=3).abs().mean(dim=(1, 2, 3))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--pairs", default="data/pairs")
    parser.add_argument("--direction", default="v2t", choices=["v2t", "t2v"])
    parser.add_argument("--variant", action="append", default=[], help="JSON object of preset overrides")
    args = parser.parse_args()
    params = load_params(args.params)
    pairs = pd.read_parquet(f"{args.pairs}/{args.direction}.parquet")
    splits = pd.read_parquet(f"{args.pairs}/splits.parquet")
    print("| overrides | test L1 | texture energy generated / real | training s |")
    print("|---|---|---|---|")
    for variant in args.variant or ["{}"]:
        settings = dict(model_settings(params), **json.loads(variant))
        size = settings["size"]
        train = load_pair_data(pairs, splits, args.direction, "all", size)
        test = load_pair_data(pairs, splits, args.direction, "all", size, split="test")
        result = train_translator(train, settings, dict(params["translation"], checkpoint_every=10**9),
                                  args.direction, "all", progress=False)
        with torch.no_grad():
            output = result.generator.eval()(to_model_range(test.inputs))
        target = to_model_range(test.targets)
        l1 = float((output - target).abs().mean())
        ratio = float(texture_energy(output).mean() / texture_energy(target).mean())
        print(f"| {variant} | {l1:.3f} | {ratio:.2f} | {result.seconds:.0f} |", flush=True)


if __name__ == "__main__":
    main()
