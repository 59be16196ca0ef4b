"""class_gan.texture and class_gan.contextual: covariance statistics and the contextual loss of a fixed random filter bank
(vtgen.core.texture), and the step with them."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from vtgen.core.texture import (contextual_loss, contextual_similarity, feature_covariance, RandomFilterBank,
                                texture_loss)
from vtgen.core.translator import TranslatorTraining

SETTINGS = {"size": 32, "ngf": 8, "ndf": 8, "kernel": 4, "discriminator": "patch", "patch_layers": 2,
            "gan_loss": "bce", "l1_weight": 100.0, "optimizer": "adam", "lr": 2e-4, "betas": [0.5, 0.999],
            "batch_size": 4, "iterations": 4, "objective": "class_gan", "r1": 0.1, "diffaugment": True,
            "mode_seeking": 1.0, "mode_seeking_pool": 1, "statistics": 0.0, "class_guidance": 0.0, "semantic": 0.0,
            "skips": None, "d_lr_ratio": 1.0, "latent": 8, "upsample": "transpose"}


def stripes(vertical: bool, shift: int = 0, side: int = 32, period: int = 6) -> torch.Tensor:
    """1 x 3 x side x side sine stripes in [-0.8, 0.8]: vertical ones vary along x."""
    axis = torch.arange(side, dtype=torch.float32) + shift
    wave = 0.8 * torch.sin(2 * torch.pi * axis / period)
    image = wave[None, :].expand(side, side) if vertical else wave[:, None].expand(side, side)
    return image[None, None].expand(1, 3, side, side).clone()


def test_feature_covariance_is_the_covariance_over_positions():
    features = torch.randn(2, 3, 4, 5, dtype=torch.float64)
    for image, covariance in zip(features, feature_covariance(features)):
        flat = image.reshape(3, 20)
        assert torch.allclose(covariance, torch.cov(flat, correction=0))


def test_the_loss_sees_orientation_and_scale_not_position():
    """A quarter-period shift of stripes costs little; turning them or halving their period costs much. (Stripes at
    a deep level's Nyquist period alias under the 2x pooling, so the period is kept well above it.)"""
    bank = RandomFilterBank()
    vertical = stripes(True, side=64, period=16)
    assert texture_loss(vertical, vertical, bank) == 0
    moved = float(texture_loss(stripes(True, shift=4, side=64, period=16), vertical, bank))
    turned = float(texture_loss(stripes(False, side=64, period=16), vertical, bank))
    finer = float(texture_loss(stripes(True, side=64, period=8), vertical, bank))
    assert moved < 0.25 * turned and moved < 0.25 * finer, (moved, turned, finer)


def test_the_bank_is_fixed_and_leaves_the_global_generator_alone():
    torch.manual_seed(1)
    state = torch.get_rng_state()
    first = RandomFilterBank()
    assert torch.equal(torch.get_rng_state(), state)
    torch.manual_seed(2)
    second = RandomFilterBank()
    assert all(torch.equal(a, b) for a, b in zip(first.state_dict().values(), second.state_dict().values()))
    assert not any(p.requires_grad for p in first.parameters()) and not list(first.parameters())


def test_an_image_descends_to_the_target_texture():
    """Gradient descent on pixels alone under the loss turns noise into the target's orientation."""
    bank, target = RandomFilterBank(), stripes(True)
    torch.manual_seed(0)
    image = (0.1 * torch.randn(1, 3, 32, 32)).requires_grad_(True)
    optimiser = torch.optim.Adam([image], lr=0.05)
    start = float(texture_loss(image.detach(), target, bank))
    for _ in range(150):
        optimiser.zero_grad()
        texture_loss(image, target, bank).backward()
        optimiser.step()
    end = float(texture_loss(image.detach(), target, bank))
    assert end < 0.2 * start, (start, end)
    grey = image.detach().mean(dim=1)[0]
    along_x = (grey[:, 1:] - grey[:, :-1]).abs().mean()  # vertical stripes change along x, not along y
    along_y = (grey[1:, :] - grey[:-1, :]).abs().mean()
    assert along_x > 2 * along_y, (along_x, along_y)


def batch(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(4, 3, 32, 32, generator=g) * 2 - 1, torch.rand(4, 3, 32, 32, generator=g) * 2 - 1,
            torch.tensor([0, 0, 1, 1]))


def weights_after_steps(settings: dict, steps: int = 2) -> list[torch.Tensor]:
    torch.manual_seed(0)
    training = TranslatorTraining(settings, "cpu", num_classes=2)
    for step in range(steps):
        training.step(*batch(step))
    return [t.clone() for t in training.generator.state_dict().values()]


@pytest.mark.parametrize("term", ["texture", "contextual"])
def test_weight_zero_is_the_step_without_the_term_and_a_weight_changes_it(term):
    without = weights_after_steps(SETTINGS)
    assert all(torch.equal(a, b) for a, b in zip(without, weights_after_steps(dict(SETTINGS, **{term: 0.0}))))
    assert not all(torch.equal(a, b) for a, b in zip(without, weights_after_steps(dict(SETTINGS, **{term: 1.0}))))


def test_contextual_similarity_of_known_sets():
    """A permutation of the targets matches every one of them (CX = 1); a single output feature can be the
    clear neighbour of one target only, so CX = 1/|Y| whatever the features (Mechrez et al. 2018, eq. 4)."""
    torch.manual_seed(0)
    targets = torch.randn(2, 8, 3, 4)
    permuted = targets.reshape(2, 8, 12)[:, :, torch.randperm(12)].reshape(2, 8, 3, 4)
    assert torch.allclose(contextual_similarity(permuted, targets), torch.ones(2), atol=1e-4)
    single = torch.randn(2, 8, 1, 1)
    assert torch.allclose(contextual_similarity(single, targets), torch.full((2,), 1 / 12))
    unrelated = contextual_similarity(torch.randn(2, 8, 3, 4), targets)
    assert ((unrelated > 1 / 12) & (unrelated < 0.9)).all(), unrelated


def streaks(seed: int = 0, side: int = 64) -> torch.Tensor:
    """1 x 3 x side x side vertical streaks: noise smoothed along y over 15 px, so no two places are alike (the
    contextual loss counts a feature that recurs exactly, as in a perfect sine grating, as matched only 1/k)."""
    noise = torch.randn(1, 1, side + 14, side, generator=torch.Generator().manual_seed(seed))
    smooth = F.avg_pool2d(noise, (15, 1), stride=1)
    return (0.8 * smooth / smooth.abs().max()).expand(1, 3, side, side).clone()


def test_the_contextual_loss_sees_local_structure_not_position():
    """Streaks rolled by whole cells of the coarsest grid cost little; turned, they cost much."""
    bank = RandomFilterBank()
    vertical = streaks()
    assert float(contextual_loss(vertical, vertical, bank)) < 1e-3
    moved = float(contextual_loss(torch.roll(vertical, 8, dims=3), vertical, bank))
    turned = float(contextual_loss(vertical.transpose(2, 3), vertical, bank))
    assert moved < 0.25 * turned, (moved, turned)


def test_an_image_descends_towards_the_target_texture_under_the_contextual_loss():
    """Pixels descended under the contextual loss come to share the target's texture statistics and, weakly, its
    orientation (measured on 2x-pooled grey: the loss reads no level finer than the bank's first)."""
    bank, target = RandomFilterBank(), streaks()
    torch.manual_seed(0)
    image = (0.1 * torch.randn(1, 3, 64, 64)).requires_grad_(True)
    optimiser = torch.optim.Adam([image], lr=0.05)
    start = float(contextual_loss(image.detach(), target, bank))
    texture_start = float(texture_loss(image.detach(), target, bank))
    for _ in range(100):
        optimiser.zero_grad()
        contextual_loss(image, target, bank).backward()
        optimiser.step()
    assert float(contextual_loss(image.detach(), target, bank)) < 0.3 * start
    assert float(texture_loss(image.detach(), target, bank)) < 0.7 * texture_start
    grey = F.avg_pool2d(image.detach().mean(dim=1, keepdim=True), 2)[0, 0]
    along_x = (grey[:, 1:] - grey[:, :-1]).abs().mean()  # vertical streaks change along x, not along y
    along_y = (grey[1:, :] - grey[:-1, :]).abs().mean()
    assert along_x > 1.1 * along_y, (along_x, along_y)
