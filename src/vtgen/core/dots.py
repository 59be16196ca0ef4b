"""Dots at fixed places: one-pixel dots drawn at the same pixel positions in every image of a set.

A generator's decoder that upsamples with strided transposed convolutions can leave such a lattice
(Odena et al. 2016); no real image has it, and the feature metrics of :mod:`vtgen.core.distribution`
barely see it. :func:`dot_map` is the mean over a set of each pixel's distance from its 3 x 3 median;
:func:`fixed_dots` counts the positions above a threshold, with a bootstrap interval over images.
Pure: no files, no parameters. Only the score stage (and benchmarks) import it, so a change here
reruns nothing else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch


def _check_images(images) -> None:
    if not isinstance(images, torch.Tensor) or images.dtype != torch.uint8 or images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images: expected uint8 images N x 3 x H x W, got "
                         f"{getattr(images, 'dtype', type(images).__name__)} {tuple(getattr(images, 'shape', ()))}")


DOT_BORDER = 2  # px cut from each side of a dot map, so every pixel kept has its whole 3 x 3 neighbourhood inside
DOT_CHUNK = 256  # images per block of per-pixel residuals


def _dot_residual_blocks(images: torch.Tensor, border: int = DOT_BORDER):
    """Yield (start, float32 ``n x P`` array) per block of :data:`DOT_CHUNK` uint8 images: each image's
    |g − m| at its P interior pixels, g its grey (channel mean) and m g's 3 x 3 median (OpenCV's; the border cut
    leaves only pixels whose whole 3 x 3 neighbourhood lies inside the image)."""
    for start in range(0, len(images), DOT_CHUNK):
        grey = images[start:start + DOT_CHUNK].float().mean(dim=1).numpy()
        median = np.stack([cv2.medianBlur(g, 3) for g in grey])
        h, w = grey.shape[-2:]
        residual = np.abs(grey - median)[:, border:h - border, border:w - border]
        yield start, residual.reshape(len(grey), -1)


def dot_map(images: torch.Tensor, border: int = DOT_BORDER) -> np.ndarray:
    """uint8 ``N x 3 x H x W`` (N >= 1, H, W > 2 ``border``) -> float64 ``(H − 2 border) x (W − 2 border)``: the mean
    over the images of |grey − its 3 x 3 median| per pixel position. A one-pixel dot drawn at the same place in
    every image (a lattice of the decoder's upsampling) stays in the mean; texture at independent places averages out."""
    _check_images(images)
    if len(images) == 0 or min(images.shape[-2:]) <= 2 * border:
        raise ValueError(f"a dot map needs at least one image larger than {2 * border} px, got {tuple(images.shape)}")
    total = sum(block.sum(axis=0, dtype=np.float64) for _, block in _dot_residual_blocks(images, border))
    h, w = images.shape[-2:]
    return (total / len(images)).reshape(h - 2 * border, w - 2 * border)


@dataclass(frozen=True)
class FixedDots:
    """Pixel positions whose :func:`dot_map` value exceeds a threshold, with a 95% bootstrap interval; see :func:`fixed_dots`."""

    count: int
    low: float
    high: float
    peak: float
    n: int


def fixed_dots(images: torch.Tensor, threshold: float, resamples: int = 200, seed: int = 0,
               level: float = 0.95) -> FixedDots:
    """How many interior pixel positions of ``images`` (uint8 ``N x 3 x H x W``) have a :func:`dot_map` value above
    ``threshold`` (grey levels): dots at fixed places. The interval is a percentile bootstrap over images (``resamples``
    draws with replacement, numpy generator seeded with ``seed``), each draw's map a weighted mean of the images'
    residuals; ``peak`` is the map's largest value."""
    n = len(images)
    _check_images(images)
    if n == 0:
        raise ValueError("fixed dots need at least one image")
    weights = np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=int(resamples)).astype(np.float32)
    total, drawn = None, None
    for start, block in _dot_residual_blocks(images):
        part, boot = block.sum(axis=0, dtype=np.float64), weights[:, start:start + len(block)] @ block
        total, drawn = (part, boot) if total is None else (total + part, drawn + boot)
    mean = total / n
    draws = ((drawn / n) > threshold).sum(axis=1)
    tail = (1 - level) / 2
    low, high = (float(v) for v in np.quantile(draws, [tail, 1 - tail])) if len(draws) else (math.nan, math.nan)
    return FixedDots(int((mean > threshold).sum()), low, high, float(mean.max()), n)
