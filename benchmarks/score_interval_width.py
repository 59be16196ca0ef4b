"""Interval width of the quadratic distribution metrics against n per class: the table behind ``score.max_per_class``.

For each target modality and class of the score benchmark's 10x inputs (built by
``benchmarks/score_scaling.py`` from ``../shared/data/vt60_subset``, real frames with crops, flips
and brightness changes), the class's real tiles (every split) are split at random into two disjoint
pools P and Q. For each n, n images are drawn from P (the reference, as half B) and n from Q, and
the score stage's metrics are computed in the classifier view (the benchmark's real-only AlexNet,
trained 2 epochs) for two candidates: Q itself (real vs real) and Q under the blurred-real baseline's
blur (sigma = side / 32). Each metric is reported as the median over classes and modalities of
its 95% interval width, with its value for both candidates (the gap between them is what the
interval has to resolve) and the seconds one candidate's metric set takes at that n.

Intervals are the score stage's: KID mean +- 1.96 std over 50 subsets of n / 2; FID bias-corrected
bootstrap over images (``score.fid_resamples`` draws); two-sample accuracy, recall and coverage Wilson
intervals.

    python benchmarks/score_interval_width.py --inputs /tmp/score_bench/x10    # after score_scaling.py --keep /tmp/score_bench
    python benchmarks/score_interval_width.py --inputs /tmp/score_bench/x10 --sizes 10 20 40 --repeats 1
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from vtgen.core import distribution as dist  # noqa: E402
from vtgen.io.classifiers import load_classifier  # noqa: E402
from vtgen.io.images import read_tiles  # noqa: E402
from vtgen.stages.score import KID_SUBSETS, TWO_SAMPLE_MIN_IMAGES, _set_metrics  # noqa: E402

METRICS = [("kid", "KID"), ("fid", "FID"), ("two_sample", "two-sample acc."), ("recall", "recall"),
           ("coverage", "coverage")]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=Path, required=True, help="a folder built by score_scaling.py (x10)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 20, 40, 80, 120, 200])
    parser.add_argument("--fid-resamples", type=int, default=50)
    parser.add_argument("--repeats", type=int, default=2, help="draws of the n images per class and size")
    args = parser.parse_args()
    torch.set_num_threads(1)
    splits = pd.read_parquet(args.inputs / "pairs/splits.parquet")
    records = []
    for modality in ("tactile", "visual"):
        model, _ = load_classifier(args.inputs / "classify" / modality / "encoder.pt")
        encoder = dist.classifier_encoder(model)
        rows = splits[splits["modality"] == modality].sort_values("path")
        images = read_tiles(list(rows["path"]), model.size)
        features = dist.image_features(encoder, images)
        blurred = dist.image_features(encoder, dist.gaussian_blur(images, dist.default_blur_sigma(images.shape[-1])))
        classes = rows["class"].to_numpy()
        for c, name in enumerate(sorted(set(classes))):
            members = np.flatnonzero(classes == name)
            rng = np.random.default_rng(c)
            order = rng.permutation(members)
            pool_p, pool_q = order[: len(order) // 2], order[len(order) // 2:]
            for n in args.sizes:
                if n > min(len(pool_p), len(pool_q)):
                    continue
                for r in range(args.repeats):
                    draw = np.random.default_rng([c, n, r])
                    p = torch.from_numpy(np.sort(draw.choice(pool_p, n, replace=False)))
                    q = torch.from_numpy(np.sort(draw.choice(pool_q, n, replace=False)))
                    reference = {"classifier": features[p], "spectrum": torch.zeros(n, 1, dtype=torch.float64)}
                    for candidate, source in (("real", features), ("blurred", blurred)):
                        started = time.perf_counter()
                        out = _set_metrics(reference, {"classifier": source[q],
                                                       "spectrum": torch.zeros(n, 1, dtype=torch.float64)},
                                           args.fid_resamples, 0)
                        seconds = time.perf_counter() - started
                        for metric, _ in METRICS:
                            value, low, high = out[("classifier", metric)]
                            records.append({"modality": modality, "class": name, "n": n, "repeat": r,
                                            "candidate": candidate, "metric": metric, "value": value,
                                            "width": high - low, "seconds": seconds})
        print(f"{modality}: done", file=sys.stderr, flush=True)
    table = pd.DataFrame(records)
    print(f"\nclassifier view, median over classes x modalities x {args.repeats} draws; real = real vs real, "
          f"blurred = the blurred-real baseline; KID subsets {KID_SUBSETS}, FID resamples {args.fid_resamples}, "
          f"two-sample test from n = {TWO_SAMPLE_MIN_IMAGES}\n")
    header = "| n per class | " + " | ".join(f"{label} width (real / blurred: value)" for _, label in METRICS)
    print(header + " | s per candidate | classes |")
    print("|---" * (len(METRICS) + 3) + "|")
    for n, part in table.groupby("n"):
        cells = []
        for metric, _ in METRICS:
            m = part[part["metric"] == metric]
            width = m[m["candidate"] == "real"]["width"].median()
            values = [m[m["candidate"] == c]["value"].median() for c in ("real", "blurred")]
            cells.append("-" if math.isnan(width) else f"{width:.3g} ({values[0]:.3g} / {values[1]:.3g})")
        seconds = part.drop_duplicates(["modality", "class", "repeat", "candidate"])["seconds"].median()
        classes = part.drop_duplicates(["modality", "class"]).shape[0]
        print(f"| {n} | " + " | ".join(cells) + f" | {seconds:.2f} | {classes} |")


if __name__ == "__main__":
    main()
