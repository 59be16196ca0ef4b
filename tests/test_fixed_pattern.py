"""Dots at fixed places (vtgen.core.dots): the dot map against scipy's median filter, the count and its interval."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
import torch

from vtgen.core import fixed_pattern
from vtgen.core.translator import fine_detail


def _grain(count: int, side: int = 32, seed: int = 0) -> torch.Tensor:
    """uint8 ``count x 3 x side x side`` grey grain (levels 100-139), no dots."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(100, 140, (count, 1, side, side), generator=generator).to(torch.uint8).expand(-1, 3, -1, -1).contiguous()


def test_dot_map_is_the_mean_absolute_residual_from_a_3x3_median_per_pixel():
    """Against scipy's median filter with replicated edges ('nearest'), on more images than one block holds."""
    images = _grain(fixed_pattern.DOT_CHUNK + 7, side=12)
    grey = images.numpy().astype(np.float64).mean(axis=1)
    median = np.stack([scipy.ndimage.median_filter(g, size=3, mode="nearest") for g in grey])
    expected = np.abs(grey - median).mean(axis=0)[2:-2, 2:-2]
    np.testing.assert_allclose(fixed_pattern.dot_map(images), expected, atol=1e-4)
    with pytest.raises(ValueError, match="larger than 4 px"):
        fixed_pattern.dot_map(images[:, :, :4, :4])


def test_fixed_dots_finds_a_dot_at_one_place_in_every_image_not_dots_that_move():
    base = _grain(16)
    fixed, moving = base.clone(), base.clone()
    fixed[:, :, 10, 20] = 255                     # one dot, same place in all 16 images
    for i in range(16):
        moving[i, :, 4 + i, 6 + i] = 255           # one dot per image, each at its own place
    threshold = 3 * float(fixed_pattern.dot_map(base).max())
    assert fixed_pattern.dot_map(fixed)[10 - 2, 20 - 2] > threshold  # reported at the dot's place, border of 2 px cut
    found = fixed_pattern.fixed_dots(fixed, threshold, resamples=50)
    assert (found.count, found.low, found.high, found.n) == (1, 1.0, 1.0, 16)  # every resample keeps the dot
    assert found.peak == pytest.approx(float(fixed_pattern.dot_map(fixed).max()))
    assert fixed_pattern.fixed_dots(moving, threshold, resamples=50).count == 0
    # a dot in 6 of 16 images: the count is 1, but resamples that draw fewer of those images lose it
    few = base.clone()
    few[:6, :, 10, 20] = 255
    partial = fixed_pattern.fixed_dots(few, threshold, resamples=200)
    assert partial.count == 1 and partial.low == 0.0 and partial.high == 1.0


def test_fixed_share_is_about_0_for_independent_detail_at_any_n_and_the_pattern_share_otherwise():
    """Grain drawn independently per image: about 0 at n = 8 and n = 64 (the uncorrected share would be about 1/n);
    one fixed pattern of the grain's energy added to every image: about 1/2; identical images: exactly 1. Each
    interval holds its estimate."""
    generator = torch.Generator().manual_seed(0)
    pattern = torch.randn(1, 1, 32, 32, generator=generator) * 20

    def images(count, with_pattern):
        grain = torch.randn(count, 1, 32, 32, generator=generator) * 20 + (pattern if with_pattern else 0)
        return (128 + grain).round().clamp(0, 255).to(torch.uint8).expand(-1, 3, -1, -1).contiguous()

    for count in (8, 64):
        found = fixed_pattern.fixed_share(images(count, False))
        assert abs(found.share) < 0.03 and found.low <= found.share <= found.high and found.n == count, found
        half = fixed_pattern.fixed_share(images(count, True))
        assert 0.4 < half.share < 0.6 and half.low <= half.share <= half.high and half.low > found.high, half
    same = images(1, True).expand(10, -1, -1, -1).contiguous()
    assert fixed_pattern.fixed_share(same).share == pytest.approx(1.0)
    # the pattern every image shares is then the whole detail: its RMS in grey levels
    detail = fixed_pattern.grey_detail(same[:1])
    assert fixed_pattern.fixed_share(same).rms == pytest.approx(float(np.sqrt((detail.astype(np.float64) ** 2).mean())), rel=1e-4)
    with pytest.raises(ValueError, match="at least 2 images"):
        fixed_pattern.fixed_share(same[:1])


def test_grey_detail_is_the_training_costs_fine_detail_of_the_grey_image():
    """The score stage's copy (OpenCV, so that it does not import the networks) equals
    :func:`vtgen.core.translator.fine_detail`, edges included."""
    images = torch.randint(0, 256, (5, 3, 17, 23), generator=torch.Generator().manual_seed(1)).to(torch.uint8)
    expected = fine_detail(images.float().mean(dim=1, keepdim=True))[:, 0].numpy()
    np.testing.assert_allclose(fixed_pattern.grey_detail(images), expected, atol=1e-4)
