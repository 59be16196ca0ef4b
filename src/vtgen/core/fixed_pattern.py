"""A fixed pattern: fine detail drawn at the same pixel positions in every image of a set.

A generator's decoder that upsamples with strided transposed convolutions can leave a lattice of
squares or one-pixel dots at the same places in every output (Odena et al. 2016); no real image has
it, and the feature metrics of :mod:`vtgen.core.distribution` barely see it.

* :func:`fixed_share`: the share of a set's fine-detail energy that sits at the same place with the
  same sign in every image (bias-corrected, so about 0 for detail at independent places at any n);
* :func:`dot_map`, :func:`fixed_dots`: one-pixel dots, the mean over a set of each pixel's distance
  from its 3 x 3 median, and the positions where it exceeds a threshold.

Each with a percentile bootstrap interval over images. Pure: no files, no parameters. Only the score
stage (and benchmarks) import it, so a change here reruns only the score and report stages.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from vtgen.core.distribution import _check_images



DOT_BORDER = 2  # px cut from each side of a dot map, so every pixel kept has its whole 3 x 3 neighbourhood inside
DOT_CHUNK = 256  # images per block of per-pixel residuals


def _resample_weights(n: int, resamples: int, seed: int) -> np.ndarray:
    """float32 ``resamples x n``: how often each of n images is drawn in each bootstrap resample (with replacement,
    numpy generator seeded with ``seed``)."""
    return np.random.default_rng(seed).multinomial(n, np.full(n, 1.0 / n), size=int(resamples)).astype(np.float32)


def _percentiles(draws: np.ndarray, level: float) -> tuple[float, float]:
    """The percentile interval of bootstrap draws at ``level``; NaNs when there are none."""
    if not len(draws):
        return math.nan, math.nan
    tail = (1 - level) / 2
    low, high = np.quantile(draws, [tail, 1 - tail])
    return float(low), float(high)


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
    _check_images(images, "images")
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
    _check_images(images, "images")
    if n == 0:
        raise ValueError("fixed dots need at least one image")
    weights = _resample_weights(n, resamples, seed)
    total, drawn = None, None
    for start, block in _dot_residual_blocks(images):
        part, boot = block.sum(axis=0, dtype=np.float64), weights[:, start:start + len(block)] @ block
        total, drawn = (part, boot) if total is None else (total + part, drawn + boot)
    mean = total / n
    draws = ((drawn / n) > threshold).sum(axis=1)
    low, high = _percentiles(draws, level)
    return FixedDots(int((mean > threshold).sum()), low, high, float(mean.max()), n)


def grey_detail(images: torch.Tensor) -> np.ndarray:
    """uint8 ``N x 3 x H x W`` -> float32 ``N x H x W``: each image's grey (channel mean) minus its 3 x 3 mean (edges
    replicated), the high-pass detail :func:`vtgen.core.translator.fine_detail` gives (tested equal; computed here with
    OpenCV's box filter so that the score stage does not import the networks)."""
    grey = images.float().mean(dim=1).numpy()
    return grey - np.stack([cv2.blur(g, (3, 3), borderType=cv2.BORDER_REPLICATE) for g in grey]) if len(grey) else grey


@dataclass(frozen=True)
class FixedShare:
    """A set's bias-corrected fixed share with a 95% bootstrap interval, and the fixed pattern's RMS in grey levels
    (sqrt of the share, at least 0, times the set's mean fine-detail energy per pixel) at each; see :func:`fixed_share`."""

    share: float
    low: float
    high: float
    rms: float
    rms_low: float
    rms_high: float
    n: int


def _share(k, sum_mean_sq, sum_energy) -> np.ndarray:
    """(Σₚ m² − k Σₚ e) / ((1 − k) Σₚ e), elementwise over draws; NaN where Σₚ e is 0 (no detail at all). For a mean
    m = Σᵢ wᵢ hᵢ / n with Σ wᵢ = n, E[m²] = μ² + k var h with k = Σ wᵢ² / n² (1/n for the sample itself), and
    e − m² estimates (1 − k) var h."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(sum_energy > 0, (sum_mean_sq - k * sum_energy) / ((1 - k) * sum_energy), np.nan)


def fixed_share(images: torch.Tensor, resamples: int = 200, seed: int = 0, level: float = 0.95) -> FixedShare:
    """s = (n Σₚ m(p)² − Σₚ e(p)) / ((n − 1) Σₚ e(p)) over the pixel positions p of ``images`` (uint8
    ``N x 3 x H x W``, N >= 2): h_i = :func:`grey_detail` of image i (its grey minus the grey's 3 x 3 mean, in grey
    levels: the detail the training's fixed-pattern costs read), m = mean_i h_i,
    e = mean_i h_i².
    With h_i = μ + ε_i this estimates Σ μ² / Σ (μ² + var ε) without bias (m² alone overestimates μ² by var ε / n):
    the share of the detail's energy that every image draws at the same place with the same sign, about 0 for detail
    at independent places and 1 for one pattern in every image; ``rms`` is that pattern's size in grey levels (how
    visible it is). Percentile bootstrap over images (``resamples``
    draws with replacement, numpy generator seeded with ``seed``; a draw that repeats an image corrects by its own
    weights, :func:`_share`)."""
    _check_images(images, "images")
    n = len(images)
    if n < 2:
        raise ValueError(f"a fixed share needs at least 2 images, got {n}")
    weights = _resample_weights(n, resamples, seed)
    total, drawn, energy = None, None, np.zeros(n)
    for start in range(0, n, DOT_CHUNK):
        detail = grey_detail(images[start:start + DOT_CHUNK]).reshape(-1, images.shape[-2] * images.shape[-1])
        energy[start:start + len(detail)] = (detail.astype(np.float64) ** 2).sum(axis=1)
        part, boot = detail.sum(axis=0, dtype=np.float64), weights[:, start:start + len(detail)] @ detail
        total, drawn = (part, boot) if total is None else (total + part, drawn + boot)
    share = float(_share(1 / n, ((total / n) ** 2).sum(), energy.sum() / n))
    weights = weights.astype(np.float64)
    draws = _share((weights ** 2).sum(axis=1) / n ** 2, ((drawn.astype(np.float64) / n) ** 2).sum(axis=1),
                   weights @ energy / n)
    draws = draws[np.isfinite(draws)]
    low, high = _percentiles(draws, level)
    per_pixel = energy.sum() / n / (images.shape[-2] * images.shape[-1])
    rms = [math.sqrt(max(v, 0.0) * per_pixel) if math.isfinite(v) else math.nan for v in (share, low, high)]
    return FixedShare(share, low, high, *rms, n)
