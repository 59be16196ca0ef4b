"""The realism score (Kynkäänniemi et al. 2019) and generate.redraws: known inputs, and draw 0 left untouched."""

import pytest
import torch
from torch import nn

from vtgen.core.realism import RealBalls, layout_features
from vtgen.core.translation import REDRAW_SEED_STRIDE, translate, translate_precise


def light_images(n: int, seed: int = 0) -> torch.Tensor:
    """Light grey tiles (about 200): one of four fixed 8 x 8 layouts each, +-5 of noise per cell, like touches of a
    bright sensor (the layouts are the same for every seed; the draw and the noise follow ``seed``)."""
    layouts = 200 + 25 * torch.randn(4, 1, 8, 8, generator=torch.Generator().manual_seed(99))
    g = torch.Generator().manual_seed(seed)
    cells = layouts[torch.randint(0, 4, (n,), generator=g)] + 5 * torch.randn(n, 1, 8, 8, generator=g)
    return cells.repeat_interleave(4, 2).repeat_interleave(4, 3).repeat(1, 3, 1, 1).clamp(0, 255).to(torch.uint8)


class SignGenerator(nn.Module):
    """A stand-in generator with an 8-channel code: its input where z[0] > 0, else a light disc on a black ground."""

    def __init__(self):
        super().__init__()
        self.latent, self.latent_map, self.size = 8, False, 32
        self.scale = nn.Parameter(torch.ones(()))
        yy, xx = torch.meshgrid(torch.arange(32), torch.arange(32), indexing="ij")
        self.register_buffer("disc", (((yy - 16) ** 2 + (xx - 16) ** 2) < 64).float())

    def forward(self, x, z):
        light = (z[:, 0] > 0).float()[:, None, None, None]
        dark = self.disc * 1.6 - 1.0  # disc at 0.6, ground at -1 (black)
        return self.scale * (light * x + (1 - light) * dark.expand_as(x))


def test_layout_features_are_each_channels_cell_means_on_unit_range():
    images = torch.zeros(2, 3, 16, 16, dtype=torch.uint8)
    images[0, 1, :8, :8] = 255  # green in the top-left quarter
    feats = layout_features(images, side=2)
    assert feats.shape == (2, 12)
    assert feats[0].tolist() == [0, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0, 0]
    assert feats[1].abs().sum() == 0
    with pytest.raises(ValueError, match="uint8"):
        layout_features(images.float())


def test_real_images_score_at_least_one_and_a_dark_ground_below():
    real = light_images(60)
    balls = RealBalls(real)
    feats = layout_features(real)
    radii = torch.cdist(feats, feats).sort(dim=1).values[:, 3]  # k = 3, itself excluded
    assert len(balls.radii) == int((radii <= radii.median()).sum())  # the widest half is dropped
    kept = radii <= radii.median()
    assert (balls.score(real[kept]) > 10).all()  # a kept centre is (about) at distance 0 from itself
    new_real = light_images(20, seed=1)
    dark = torch.zeros(5, 3, 32, 32, dtype=torch.uint8)
    assert (balls.score(dark) < 0.2).all()
    assert balls.score(new_real).min() > 2 * balls.score(dark).max()
    with pytest.raises(ValueError, match="more than k"):
        RealBalls(real[:3])


def test_redraws_zero_is_translate_bit_for_bit_and_redraws_replace_only_failed_draws():
    torch.manual_seed(0)
    generator, real = SignGenerator(), RealBalls(light_images(60))
    inputs = light_images(40, seed=2)
    plain = translate(generator, inputs, seed=5)
    same, kept = translate_precise(generator, inputs, real, 0, seed=5)
    assert torch.equal(same, plain) and not kept.any()

    out, kept = translate_precise(generator, inputs, real, 6, seed=5)
    first_open = real.score(plain) < 1
    first_dark = plain[:, 0, 0, 0] == 0  # the disc's black ground
    assert 5 <= int(first_dark.sum()) <= 35  # about half the first draws are the dark disc
    assert (first_open | ~first_dark).all()  # every dark draw is outside the real balls
    assert torch.equal(out[~first_open], plain[~first_open]) and not kept[~first_open].any()
    assert (out[:, 0, 0, 0] == 0).sum() < first_dark.sum() // 4  # most dark draws were replaced
    assert real.score(out).mean() > real.score(plain).mean()
    # draw d of the open inputs is translate's at seed + d * stride, in their order
    open_ = first_open.nonzero().flatten()
    second = translate(generator, inputs[open_], seed=5 + REDRAW_SEED_STRIDE)
    took_second = kept[open_] == 1
    assert torch.equal(out[open_][took_second], second[took_second])
    again, kept_again = translate_precise(generator, inputs, real, 6, seed=5)
    assert torch.equal(again, out) and torch.equal(kept_again, kept)  # deterministic


def test_redraws_do_nothing_without_a_code_or_at_psi_zero():
    generator, real = SignGenerator(), RealBalls(light_images(60))
    inputs = light_images(10, seed=3)
    out, kept = translate_precise(generator, inputs, real, 4, seed=1, truncation=0.0)
    assert torch.equal(out, translate(generator, inputs, seed=1, truncation=0.0)) and not kept.any()
