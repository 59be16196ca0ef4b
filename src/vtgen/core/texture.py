"""Texture statistics of a fixed random filter bank, for class-paired translation (``class_gan.texture``).

A touch of a fabric is a texture: what tells its class is the orientation, scale and contrast of its relief
strokes, not where they lie. Gram matrices of convolutional features capture that and nothing of the layout
(Gatys et al. 2015); a network need not be trained for them to do so: multi-scale random filters
generate natural textures about as well as a trained VGG (Ustyuzhaninov et al. 2017, "What does it take to
generate natural textures?"). A random bank cannot be fooled the way a trained classifier can (its filters
were never fitted to the classes), and it needs no weights from outside.

The term compares an output's statistics with those of a real image of its class, so its optimum is the
class's typical texture statistics: a shift-invariant summary, which cannot pull the pixels to the class
mean image (the collapse a pixel loss to a random partner of the class causes).
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
