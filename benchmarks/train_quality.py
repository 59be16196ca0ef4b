"""Final aligned Colour-SSIM of fp32 against bf16 training, over seeds, on the pipeline's real pairs.

For each seed and precision, ``train_translator`` (fused optimiser step, D frozen in the G step)
trains one direction on the training split of ``data/pairs`` for ``--iterations`` steps; the generator then
translates the aligned test pairs in eval mode (as the generate stage does) and each uint8 output
is scored against its own ground truth with ``vtgen.core.metrics.colour_ssim`` (as the score stage's
aligned score). The table gives the per-seed scores, each precision's mean and seed spread
(min-max and standard deviation), and whether bf16's mean lies inside fp32's seed range.

    python benchmarks/train_quality.py --iterations 500                      # fast preset, seeds 0 1 2, v2t
    python benchmarks/train_quality.py --setting mid32 --iterations 300 --seeds 0 1 2 3
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import numpy as np

from vtgen.io.params import load_params
from vtgen.stages.generate import translate
from vtgen.io.tables import read_table
from vtgen.core.metrics import colour_ssim
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.stages.train import load_pair_data, pairs_in, train_translator
from vtgen.io.images import read_tiles

try:  # run as a script from the repository root or as a module
    from train_speed import settings_for
except ImportError:  # pragma: no cover
    from benchmarks.train_speed import settings_for


def test_split(pairs, size: int):
    """Inputs and ground truths (uint8 N x 3 x S x S) of the aligned test pairs, in a fixed order."""
    test = pairs_in(pairs, "test", "all")
    test = test[test["aligned"]].sort_values(["class", "input_path"])
    if test.empty:
        raise SystemExit("the pair table has no aligned test pairs to score")
    return read_tiles(list(test["input_path"]), size), read_tiles(list(test["target_path"]), size)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", default="params.yaml")
    parser.add_argument("--pairs", default="data/pairs", help="output folder of the pairs stage")
    parser.add_argument("--setting", default="fast", help="a preset of params.yaml, or mid32 / mid64 (see train_speed.py)")
    parser.add_argument("--direction", default="v2t", choices=list(DIRECTIONS))
    parser.add_argument("--iterations", type=int, default=500)
    parser.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2])
    parser.add_argument("--precisions", nargs="*", default=["fp32", "bf16"])
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: translation.threads)")
    args = parser.parse_args()

    params = load_params(args.params)
    settings = dict(settings_for(params, args.setting), iterations=args.iterations)
    run = dict(params["translation"], device="cpu", checkpoint_every=10**9, log_every=args.iterations, resume=False)
    if args.threads:
        run["threads"] = args.threads
    pairs_dir = Path(args.pairs)
    if not (pairs_dir / f"{args.direction}.parquet").is_file():
        raise SystemExit(f"{pairs_dir}: no {args.direction}.parquet (run the pipeline up to the pairs stage first)")
    pairs = read_table(pairs_dir / f"{args.direction}.parquet", PAIR_COLUMNS, f"a {args.direction} pair table")
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    data = load_pair_data(pairs, splits, args.direction, "all", settings["size"])
    inputs, truths = test_split(pairs, settings["size"])
    truths = truths.permute(0, 2, 3, 1).numpy()
    print(f"{args.direction}, setting '{args.setting}' ({settings['size']} px, ngf/ndf {settings['ngf']}/{settings['ndf']}, "
          f"batch {settings['batch_size']}), {args.iterations} iterations, {len(data.targets)} training pairs, "
          f"{len(truths)} aligned test pairs, {run['threads']} threads\n", flush=True)

    scores: dict[str, dict[int, float]] = {p: {} for p in args.precisions}
    seconds: dict[str, list[float]] = {p: [] for p in args.precisions}
    for seed in args.seeds:
        for precision in args.precisions:
            result = train_translator(data, settings, dict(run, seed=seed, precision=precision), args.direction, "all",
                                      progress=False)
            outputs = translate(result.generator.eval(), inputs).permute(0, 2, 3, 1).numpy()
            scores[precision][seed] = float(np.mean(colour_ssim(outputs, truths, 255.0)))
            seconds[precision].append(result.seconds)
            print(f"seed {seed} {precision}: Colour-SSIM {scores[precision][seed]:.4f} "
                  f"({result.seconds / args.iterations:.3f} s/it)", flush=True)

    print("\n| seed | " + " | ".join(args.precisions) + " |")
    print("|---|" + "---|" * len(args.precisions))
    for seed in args.seeds:
        print(f"| {seed} | " + " | ".join(f"{scores[p][seed]:.4f}" for p in args.precisions) + " |")
    summary = {}
    for p in args.precisions:
        values = list(scores[p].values())
        summary[p] = (statistics.mean(values), min(values), max(values),
                      statistics.stdev(values) if len(values) > 1 else 0.0)
    print("| mean | " + " | ".join(f"{summary[p][0]:.4f}" for p in args.precisions) + " |")
    print("| spread (min-max) | " + " | ".join(f"{summary[p][1]:.4f}-{summary[p][2]:.4f}" for p in args.precisions) + " |")
    print("| std over seeds | " + " | ".join(f"{summary[p][3]:.4f}" for p in args.precisions) + " |")
    print("| s/it (median) | " + " | ".join(f"{statistics.median(seconds[p]) / args.iterations:.3f}"
                                            for p in args.precisions) + " |")
    if "fp32" in summary:
        _, low, high, _ = summary["fp32"]
        for p in args.precisions:
            if p != "fp32":
                mean = summary[p][0]
                print(f"\n{p} mean {mean:.4f} {'lies within' if low <= mean <= high else 'lies OUTSIDE'} "
                      f"fp32's seed range {low:.4f}-{high:.4f} (difference of means {mean - summary['fp32'][0]:+.4f})")


if __name__ == "__main__":
    main()
