"""Dots at fixed places (vtgen.core.dots): the dot map against scipy's median filter, the count and its interval."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import torch

from vtgen.core import dots


def _grain(count: int, side: int = 32, seed: int = 0) -> torch.Tensor:
    """uint8 ``count x 3 x side x side`` grey grain (levels 100-139), no dots."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(100, 140, (count, 1, side, side), generator=generator).to(torch.uint8).expand(-1, 3, -1, -1).contiguous()


def test_dot_map_is_the_mean_absolute_residual_from_a_3x3_median_per_pixel():
    """Against scipy's median filter with replicated edges ('nearest'), on more images than one block holds."""
    images = _grain(dots.DOT_CHUNK + 7, side=12)
    grey = images.numpy().astype(np.float64).mean(axis=1)
    median = np.stack([scipy.ndimage.median_filter(g, size=3, mode="nearest") for g in grey])
    expected = np.abs(grey - median).mean(axis=0)[2:-2, 2:-2]
    np.testing.assert_allclose(dots.dot_map(images), expected, atol=1e-4)
    with pytest.raises(ValueError, match="larger than 4 px"):
        dots.dot_map(images[:, :, :4, :4])


def test_fixed_dots_finds_a_dot_at_one_place_in_every_image_not_dots_that_move():
    base = _grain(16)
    fixed, moving = base.clone(), base.clone()
    fixed[:, :, 10, 20] = 255                     # one dot, same place in all 16 images
    for i in range(16):
        moving[i, :, 4 + i, 6 + i] = 255           # one dot per image, each at its own place
    threshold = 3 * float(dots.dot_map(base).max())
    assert dots.dot_map(fixed)[10 - 2, 20 - 2] > threshold  # reported at the dot's place, border of 2 px cut
    found = dots.fixed_dots(fixed, threshold, resamples=50)
    assert (found.count, found.low, found.high, found.n) == (1, 1.0, 1.0, 16)  # every resample keeps the dot
    assert found.peak == pytest.approx(float(dots.dot_map(fixed).max()))
    assert dots.fixed_dots(moving, threshold, resamples=50).count == 0
    # a dot in 6 of 16 images: the count is 1, but resamples that draw fewer of those images lose it
    few = base.clone()
    few[:6, :, 10, 20] = 255
    partial = dots.fixed_dots(few, threshold, resamples=200)
    assert partial.count == 1 and partial.low == 0.0 and partial.high == 1.0
