"""A reader of an image's class from hand-crafted colour and texture features (``translation.inferred_reader:
features``), for ``conditioning: inferred``.

On object data with one or two physical instances per class, the classify stage's network, trained from scratch
on a hundred images, reads *new* instances barely above chance, where colour and texture statistics carry over;
on the fabric touches the network reads better (measured in benchmarks/README.md, Twenty-third round).

Features (:func:`handcrafted_features`), on each tile resized (anti-aliased) to :data:`FEATURE_SIDE` px:

* an HSV histogram, 8 x 4 x 4 bins (hue, saturation, value), as shares of the pixels;
* a grey-level histogram, 16 bins, as shares;
* HOG (Dalal & Triggs 2005): 9 orientations, 16 px cells, 2 x 2-cell blocks (L2-Hys);
* the histogram of uniform local binary patterns (Ojala et al. 2002; 8 neighbours, radius 1), as shares.

The classifier is a multinomial logistic regression on the standardised features (scikit-learn, L2 weight
1 / C), fitted once; the module keeps only its numbers (means, scales, weights, biases), so a model file needs
no scikit-learn object to be read back. Each feature's scale is its training standard deviation, but at least
:data:`SCALE_FLOOR` times the median feature's: a histogram bin that almost no training image fills (a colour no
training object has) would otherwise turn a new image that fills it into a value hundreds of spreads out, and
that one feature would decide the reading (the smoothing of per-feature variances in Gaussian naive Bayes serves
the same end). On vt60_subset's new object instances it reads the photos better; on the touches and the synthetic
fabrics it changed nothing beyond the noise (benchmarks/README.md, Sixty-second round).
"""

from __future__ import annotations

import numpy as np
import torch
from skimage import color, feature, transform
from torch import nn

FEATURE_SIDE = 64
SCALE_FLOOR = 0.1  # no feature's scale below this share of the median feature's standard deviation
_HSV_BINS, _GREY_BINS, _LBP_BINS = (8, 4, 4), 16, 10
_HOG = {"orientations": 9, "pixels_per_cell": (16, 16), "cells_per_block": (2, 2)}
FEATURE_COUNT = (int(np.prod(_HSV_BINS)) + _GREY_BINS + _LBP_BINS
                 + 9 * 4 * (FEATURE_SIDE // 16 - 1) ** 2)  # HOG: 9 orientations x 4 cells per block x 3 x 3 blocks


def handcrafted_features(images: torch.Tensor) -> np.ndarray:
    """uint8 N x 3 x S x S tiles -> float64 N x :data:`FEATURE_COUNT` (the module docstring's features)."""
    if images.dim() != 4 or images.shape[1] != 3 or images.dtype != torch.uint8:
        raise ValueError(f"expected uint8 N x 3 x S x S tiles, got {tuple(images.shape)} {images.dtype}")
    rows = []
    for image in images.cpu().permute(0, 2, 3, 1).numpy():
        rgb = transform.resize(image / 255.0, (FEATURE_SIDE, FEATURE_SIDE), anti_aliasing=True)
        hsv, _ = np.histogramdd(color.rgb2hsv(rgb).reshape(-1, 3), bins=_HSV_BINS, range=((0, 1),) * 3)
        grey = color.rgb2gray(rgb)
        patterns = feature.local_binary_pattern((grey * 255).astype(np.uint8), 8, 1, "uniform")
        rows.append(np.concatenate([hsv.ravel() / grey.size,
                                    np.histogram(grey, _GREY_BINS, (0, 1))[0] / grey.size,
                                    feature.hog(grey, **_HOG),
                                    np.histogram(patterns, _LBP_BINS, (0, _LBP_BINS))[0] / grey.size]))
    return np.stack(rows) if rows else np.zeros((0, FEATURE_COUNT))


class FeatureReader(nn.Module):
    """uint8 N x 3 x S x S -> float32 logits N x K: ``linear((features - mean) / scale)``."""

    def __init__(self, num_classes: int):
        super().__init__()
        self.register_buffer("mean", torch.zeros(FEATURE_COUNT, dtype=torch.float64))
        self.register_buffer("scale", torch.ones(FEATURE_COUNT, dtype=torch.float64))
        self.linear = nn.Linear(FEATURE_COUNT, num_classes, dtype=torch.float64)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        features = torch.from_numpy(handcrafted_features(images)).to(self.mean.device)
        return self.linear((features - self.mean) / self.scale).float()


def fit_feature_reader(images: torch.Tensor, labels: torch.Tensor, num_classes: int,
                       inverse_penalty: float = 0.1, scale_floor: float = SCALE_FLOOR) -> FeatureReader:
    """A :class:`FeatureReader` fitted on uint8 ``images`` with class indices ``labels`` (0..num_classes-1, at
    least two distinct): standardisation, (f - mean) / max(std, ``scale_floor`` x median std), then an
    L2-penalised multinomial logistic regression (C = ``inverse_penalty``; lbfgs, deterministic)."""
    from sklearn.linear_model import LogisticRegression  # here, not at the top: scikit-learn takes a second to import
    from sklearn.preprocessing import StandardScaler

    present = sorted(set(labels.tolist()))
    if len(present) < 2:
        raise ValueError(f"the feature reader needs images of at least 2 classes, got {present}")
    features = handcrafted_features(images)
    scaler = StandardScaler().fit(features)
    scale = np.maximum(scaler.scale_, scale_floor * np.median(scaler.scale_))
    model = LogisticRegression(C=inverse_penalty, max_iter=3000).fit((features - scaler.mean_) / scale,
                                                                     labels.numpy())
    weights = np.zeros((num_classes, FEATURE_COUNT))
    biases = np.full(num_classes, -1e4)  # a class with no training image is never read
    if len(model.classes_) == 2:  # scikit-learn keeps one row: p(second) = sigmoid(w x + b)
        weights[model.classes_[1]], biases[model.classes_[1]] = model.coef_[0], model.intercept_[0]
        biases[model.classes_[0]] = 0.0
    else:
        weights[model.classes_], biases[model.classes_] = model.coef_, model.intercept_
    reader = FeatureReader(num_classes)
    with torch.no_grad():
        reader.mean.copy_(torch.from_numpy(scaler.mean_))
        reader.scale.copy_(torch.from_numpy(scale))
        reader.linear.weight.copy_(torch.from_numpy(weights))
        reader.linear.bias.copy_(torch.from_numpy(biases))
    return reader.eval()
