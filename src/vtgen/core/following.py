"""Do a generator's outputs follow their inputs within a class? A Mantel test stratified by class.

The score stage's input-following check (docs/evaluation.md, Input following): a diversity ratio can be met by a
generator that varies with its noise alone; this asks whether two outputs of a class lie further apart when their
inputs do. Kept apart from :mod:`vtgen.core.distribution` (whose exact distances it uses), which training imports,
so that this check can change without retraining a model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vtgen.core.distribution import pairwise_distances

LAYOUT_SIDE = 16  # the view of the input-following check: greyscale 16 x 16 means (where light and dark lie, not grain)


@dataclass(frozen=True)
class FollowingResult:
    """Within-class Mantel correlation of input and output distances; see :func:`input_following`."""

    r: float
    null_low: float
    null_high: float
    p: float
    per_class: dict  # class -> (r, images) for each class that counts
    images: int
    pairs: int


def input_following(inputs, outputs, classes, permutations: int = 999, seed: int = 0,
                    level: float = 0.95) -> FollowingResult:
    """Do a generator's outputs follow their inputs within a class? Row i of ``outputs`` was made from row i of
    ``inputs`` (features ``N x D`` each, e.g. :func:`vtgen.core.distribution.grey_pixels` at LAYOUT_SIDE; the two D may differ).

    For every class with at least 3 rows, the Euclidean distances of all pairs of its inputs and of the same pairs'
    outputs are standardised within the class; ``r`` is the mean product over all pairs of all classes (the
    pair-weighted mean of the per-class Pearson correlations: a Mantel test, Mantel 1967, stratified by class).
    Distances *between* classes are never used, so a generator that only draws its input's class scores about 0;
    one whose outputs move with their inputs scores above. The null: the outputs' rows permuted within each class
    (``permutations`` draws, numpy generator seeded with ``seed``); ``null_low``/``null_high`` its central ``level``
    band, ``p`` the one-sided permutation p-value (1 + draws at least r) / (1 + draws). A class whose input or
    output distances are all equal does not count; NaNs when no class counts."""
    x, y, classes = inputs, outputs, np.asarray(classes)
    if not len(x) == len(y) == len(classes):
        raise ValueError(f"the input-following check needs one class per input and output row, got "
                         f"{len(x)} inputs, {len(y)} outputs, {len(classes)} classes")
    blocks, per_class = [], {}
    for name in sorted(set(classes.tolist())):
        rows = np.flatnonzero(classes == name)
        if len(rows) < 3:
            continue
        upper = np.triu_indices(len(rows), 1)
        d_in, d_out = (pairwise_distances(v[rows], v[rows]).numpy() for v in (x, y))
        a, b = d_in[upper], d_out[upper]
        if a.std() == 0 or b.std() == 0:
            continue
        z_in = (a - a.mean()) / a.std()
        per_class[name] = (float(np.mean(z_in * (b - b.mean()) / b.std())), len(rows))
        blocks.append((z_in, d_out, upper))
    if not blocks:
        return FollowingResult(math.nan, math.nan, math.nan, math.nan, {}, 0, 0)

    def statistic(orders) -> float:
        total = 0.0
        for (z_in, d_out, upper), order in zip(blocks, orders):
            b = d_out[order][:, order][upper]
            total += float(np.sum(z_in * (b - b.mean()) / b.std()))
        return total / sum(len(z) for z, _, _ in blocks)

    r = statistic([np.arange(len(d)) for _, d, _ in blocks])
    rng = np.random.default_rng(seed)
    null = np.array([statistic([rng.permutation(len(d)) for _, d, _ in blocks]) for _ in range(int(permutations))])
    tail = (1 - level) / 2
    low, high = (float(v) for v in np.quantile(null, [tail, 1 - tail])) if len(null) else (math.nan, math.nan)
    p = float((1 + np.sum(null >= r - 1e-12)) / (1 + len(null)))
    return FollowingResult(r, low, high, p, per_class, sum(n for _, n in per_class.values()),
                           sum(len(z) for z, _, _ in blocks))
