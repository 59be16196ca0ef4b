"""Confusion matrices of the real-only classifiers, and what they say a translation could score.

The realistic GAN-test (docs/evaluation.md) asks how recognisable translations would be were they real
held-out images of the target modality: no image is generated, only the two classifiers' confusions on
real test images are combined.
"""

from __future__ import annotations

import numpy as np


def confusion_counts(predictions: list[np.ndarray], labels: np.ndarray, num_classes: int) -> np.ndarray:
    """Confusion matrix of one or more runs on the same images, averaged over the runs: entry [c, k] is the
    mean number of images of true class c predicted as k (rows true class, columns predicted)."""
    matrix = np.zeros((num_classes, num_classes))
    for predicted in predictions:
        np.add.at(matrix, (np.asarray(labels, int), np.asarray(predicted, int)), 1.0)
    return matrix / max(len(predictions), 1)


def realistic_gan_test(input_confusion: np.ndarray, judge_confusion: np.ndarray, told_class: bool) -> float | None:
    """The GAN-test that real held-out target images would get in place of the translations: each input of
    true class c is replaced by a real target image of class k, k = c when the generator is told the class,
    else the class the input modality's real-only classifier reads from the input; the judge (the target
    modality's real-only classifier) calls that image c with probability P[k, c], its confusion's row k
    normalised. Returns sum_{c,k} N[c,k] P[k,c] / sum N (N = ``input_confusion``, counts, rows true class),
    an expectation over the inputs; None when a needed row of ``judge_confusion`` is empty or nothing was read."""
    counts, judged = np.asarray(input_confusion, float), np.asarray(judge_confusion, float)
    if counts.shape != judged.shape or counts.sum() <= 0:
        return None
    replaced_by = np.diag(counts.sum(axis=1)) if told_class else counts  # [true class c, class k of the image]
    row_totals = judged.sum(axis=1)
    if np.any(row_totals[replaced_by.sum(axis=0) > 0] <= 0):
        return None
    probability = judged / np.where(row_totals > 0, row_totals, 1.0)[:, None]  # P[k, c]
    return float((replaced_by * probability.T).sum() / counts.sum())
