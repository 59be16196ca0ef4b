"""The input-following check (vtgen.core.following): a Mantel test stratified by class."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.spatial

from vtgen.core.following import input_following


def test_input_following_reads_dependence_within_a_class_not_the_class_offsets():
    """Three classes of 12 inputs, far apart. Outputs that are a rotation and scaling of their inputs (every
    within-class distance x 2) follow them: r = 1 and no shuffle reaches it. Outputs that only carry their class
    (a large class offset plus independent noise) score inside the shuffles' band although the class offsets make
    every between-class distance of inputs and outputs agree: only within-class pairs count. Half-and-half lies
    between."""
    rng = np.random.default_rng(5)
    classes = np.repeat(np.array(["a", "b", "c"]), 12)
    offsets = {"a": 0.0, "b": 100.0, "c": 200.0}
    inputs = rng.normal(size=(36, 6)) * 3 + np.array([offsets[c] for c in classes])[:, None]
    rotation, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    following = 2 * inputs @ rotation + 500.0
    result = input_following(inputs, following, classes, permutations=199, seed=0)
    assert result.r == pytest.approx(1.0, abs=1e-12) and result.p == pytest.approx(1 / 200)
    assert result.null_high < 0.5 and result.images == 36 and result.pairs == 3 * 66
    assert set(result.per_class) == {"a", "b", "c"} and all(r == pytest.approx(1.0) for r, _ in result.per_class.values())

    class_only = rng.normal(size=(36, 4)) + 10 * np.array([offsets[c] for c in classes])[:, None]
    result = input_following(inputs, class_only, classes, permutations=199, seed=0)
    assert result.null_low < result.r < result.null_high and result.p > 0.05
    # the same sets with the class offsets read across classes would agree almost perfectly
    assert np.corrcoef(scipy.spatial.distance.pdist(inputs), scipy.spatial.distance.pdist(class_only))[0, 1] > 0.9

    partly = inputs + rng.normal(size=inputs.shape) * 3
    result = input_following(inputs, partly, classes, permutations=199, seed=0)
    assert 0.2 < result.r < 0.9 and result.p == pytest.approx(1 / 200)


def test_input_following_skips_classes_it_cannot_read_and_checks_its_rows():
    rng = np.random.default_rng(6)
    inputs = rng.normal(size=(8, 3))
    # class "a": 6 rows, outputs all one image (no spread: does not count); class "b": 2 rows (no pair of pairs)
    classes = np.array(["a"] * 6 + ["b"] * 2)
    outputs = np.zeros((8, 3))
    result = input_following(inputs, outputs, classes, permutations=10)
    assert math.isnan(result.r) and result.per_class == {} and result.images == 0
    with pytest.raises(ValueError, match="one class per input and output row"):
        input_following(inputs, outputs[:7], classes)
