"""Texture statistics of a fixed random filter bank, for class-paired translation (``class_gan.texture``).

A touch of a fabric is a texture: what tells its class is the orientation, scale and contrast of its relief
strokes, not where they lie. Gram matrices of convolutional features capture that and nothing of the layout
(Gatys et al. 2015); a network need not be trained for them to do so: multi-scale random filters
generate natural textures about as well as a trained VGG (Ustyuzhaninov et al. 2017, "What does it take to
generate natural textures?"). A random bank cannot be fooled the way a trained classifier can (its filters
were never fitted to the classes), and it needs no weights from outside.

The term compares an output's statistics with those of a real image of its class, so its optimum is the
class's typical texture statistics: a shift-invariant summary, which cannot pull the pixels to the class
mean image (the collapse a pixel loss to a random partner of the class causes). The contextual loss
(``class_gan.contextual``) reads the same bank's features one by one instead of their summary.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

TEXTURE_WIDTH = 64   # random filters per level
TEXTURE_LEVELS = 3   # 3x3 levels, each on a 2x average-pooled copy of the last: receptive fields 3 to 14 px
TEXTURE_SEED = 0     # the bank's weights come from a generator of their own (torch's global one is not drawn from)


class RandomFilterBank(nn.Module):
    """``levels`` levels of ``width`` fixed random 3x3 filters (He-normal, reflection-padded, ReLU), each level on
    the 2x average-pooled output of the last. Weights are buffers: never trained, rebuilt from ``seed``."""

    def __init__(self, channels: int = 3, width: int = TEXTURE_WIDTH, levels: int = TEXTURE_LEVELS,
                 seed: int = TEXTURE_SEED) -> None:
        super().__init__()
        draw = torch.Generator().manual_seed(seed)
        sources = [channels] + [width] * (levels - 1)
        for level, source in enumerate(sources):
            weight = torch.randn(width, source, 3, 3, generator=draw) * math.sqrt(2.0 / (source * 9))
            self.register_buffer(f"weight_{level}", weight)
        self.levels = levels

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The feature map of every level for images ``x`` (N x channels x H x W), finest first."""
        features = []
        for level in range(self.levels):
            if level:
                x = F.avg_pool2d(x, 2)
            x = F.relu(F.conv2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), getattr(self, f"weight_{level}")))
            features.append(x)
        return features


def feature_covariance(features: torch.Tensor) -> torch.Tensor:
    """C = (F − μ)(F − μ)ᵀ / (H·W) per image, F the C x (H·W) feature matrix and μ its mean over positions: the
    Gram matrix of Gatys et al. 2015 (eq. 3) of the centred features, N x C x C. Centring drops the mean
    response, which dominates a ReLU bank's Gram matrix: on the synthetic touches a nearest class centroid
    reads the class right 0.67 of the time from the covariances and 0.30 from the raw Gram matrices
    (n = 144 test touches, 12 classes, the default bank; the real-only AlexNet: 0.69; benchmarks/README.md)."""
    n, c, h, w = features.shape
    flat = features.reshape(n, c, h * w)
    flat = flat - flat.mean(dim=2, keepdim=True)
    return flat @ flat.transpose(1, 2) / (h * w)


def texture_loss(outputs: torch.Tensor, targets: torch.Tensor, bank: RandomFilterBank) -> torch.Tensor:
    """(1/L) Σ_l mean over images of ‖C_l(o) − C_l(t)‖_F / ‖C_l(t)‖_F, over the L levels of ``bank``, each image of
    ``outputs`` against the image of ``targets`` in its row (:func:`feature_covariance`; the style loss of Gatys et
    al. 2015, eq. 4-5, as a relative distance, not squared: the squared form grows with the fourth power of the
    output's contrast, and at weight 10 it drove the generator's outputs to saturation within 700 steps).
    ``targets`` is data (detached)."""
    with torch.no_grad():
        target_stats = [feature_covariance(f) for f in bank(targets.detach().float())]
    total = outputs.new_zeros((), dtype=torch.float32)
    for feature, target in zip(bank(outputs.float()), target_stats):
        gap = torch.linalg.matrix_norm(feature_covariance(feature) - target)
        total = total + (gap / torch.linalg.matrix_norm(target).clamp_min(1e-12)).mean()
    return total / len(target_stats)


CONTEXTUAL_LEVELS = (1, 2)    # bank levels the contextual loss compares: receptive fields 8 and 14 px
CONTEXTUAL_SIDE = 16          # a map is read at every k-th row and column so that its side is at most this: 256
                              # positions, a 256 x 256 similarity per image (all 1,024 of level 1 at 64 px: 4x the time)
CONTEXTUAL_BANDWIDTH = 0.5    # h of Mechrez et al. 2018, eq. 3 (their value)


def contextual_similarity(outputs: torch.Tensor, targets: torch.Tensor,
                          bandwidth: float = CONTEXTUAL_BANDWIDTH) -> torch.Tensor:
    """CX(X, Y) per image, X the output and Y the target feature maps (N x C x H x W each): with features centred
    on Y's mean, d_ij the cosine distance of output feature i to target feature j,
    d̃_ij = d_ij / (min_k d_ik + 1e-5), w_ij = exp((1 − d̃_ij)/h), CX_ij = w_ij / Σ_k w_ik and
    CX = (1/|Y|) Σ_j max_i CX_ij (Mechrez et al. 2018, "The contextual loss for image transformation with
    non-aligned data", eq. 1-4). 1 when every target feature is the clear nearest neighbour of some output
    feature, wherever it lies; near 0 when the two sets share nothing. Returns N values in (0, 1]."""
    n, c = outputs.shape[:2]
    x = outputs.reshape(n, c, -1)
    y = targets.reshape(n, c, -1)
    centre = y.mean(dim=2, keepdim=True)
    x = F.normalize(x - centre, dim=1)
    y = F.normalize(y - centre, dim=1)
    distance = (1 - x.transpose(1, 2) @ y).clamp_min(0)                     # N x |X| x |Y|
    relative = distance / (distance.min(dim=2, keepdim=True).values + 1e-5)
    affinity = torch.softmax((1 - relative) / bandwidth, dim=2)             # w_ij / Σ_k w_ik, computed stably
    return affinity.max(dim=1).values.mean(dim=1)


def contextual_loss(outputs: torch.Tensor, targets: torch.Tensor, bank: RandomFilterBank,
                    levels: tuple[int, ...] = CONTEXTUAL_LEVELS) -> torch.Tensor:
    """(1/L) Σ_l mean over images of −log CX(φ_l(o), φ_l(t)) (:func:`contextual_similarity`), φ_l the ``levels`` of
    ``bank``, each read on a grid of at most :data:`CONTEXTUAL_SIDE` squared positions: each output against the
    image of ``targets`` in its row. Where :func:`texture_loss` matches a texture's summary, this asks every local
    feature of the real image to be present somewhere in the output, at any place, so the output is built of the
    class's own local structures without being aligned with the image (the contextual loss of Mechrez et al.
    2018, on random filters in place of VGG). ``targets`` is data."""
    with torch.no_grad():
        target_features = bank(targets.detach().float())
    output_features = bank(outputs.float())
    total = outputs.new_zeros((), dtype=torch.float32)
    for level in levels:
        every = max(1, output_features[level].shape[-1] // CONTEXTUAL_SIDE)
        row, column = (int(i) for i in torch.randint(every, (2,)))  # a fresh grid each call: every place is read in turn
        similarity = contextual_similarity(output_features[level][..., row::every, column::every],
                                           target_features[level][..., row::every, column::every])
        total = total - torch.log(similarity.clamp_min(1e-12)).mean()
    return total / len(levels)
