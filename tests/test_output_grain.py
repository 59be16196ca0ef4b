"""class_gan.output_grain: one grain map per image after the output's tanh, with a learned strength. That it starts as
the identity, that eval mode gives an image the same grain in any batch and different images different grain, that
the output stays in [-1, 1], its off switch and ResNet refusal, and a trained generator that keeps it."""

from __future__ import annotations

import copy

import pytest
import torch

from test_class_gan import batch, fast_class_gan_settings, reloads_as_trained, SETTINGS
from vtgen.core.models import build_generator, content_seeds, OutputGrain, UNetGenerator
from vtgen.core.translator import TranslatorTraining
from vtgen.stages.train import objective_settings


def levels(n: int, seed: int) -> torch.Tensor:
    """n images of 3 x 16 x 16 on uint8 levels, in model range."""
    g = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 16, 16), generator=g).float() / 127.5 - 1


def test_seeds_follow_the_image_not_its_place_in_the_batch():
    a, b = levels(2, 0), levels(1, 1)
    assert content_seeds(torch.cat([a, b]))[:2] == content_seeds(a) == content_seeds(torch.cat([b, a]))[1:]
    changed = a.clone()
    changed[0, 2, 15, 15] += 1 / 127.5  # one level at the last pixel
    assert content_seeds(changed)[0] != content_seeds(a)[0]
    assert len(set(content_seeds(levels(64, 2)))) == 64


def test_grain_starts_as_the_identity_and_adds_one_map_per_image_alike_to_every_channel_within_range():
    layer = OutputGrain()
    y = torch.rand(2, 3, 8, 8) * 1.6 - 0.8  # inside (-1, 1): the clamp leaves it as it is
    assert torch.equal(layer(y), y) and torch.equal(layer(y, [5, 6]), y)
    with torch.no_grad():
        layer.strength.fill_(0.02)
    added = layer(y, [5, 6]) - y
    assert torch.allclose(added[:, 0], added[:, 2], atol=1e-6) and torch.allclose(added[:, 1], added[:, 2], atol=1e-6)
    assert 0.01 < added.std().item() < 0.03  # the map's N(0, 1) scaled by the strength
    assert not torch.allclose(added[0, 1], added[1, 1])  # a map per image
    assert torch.equal(layer(y, [5, 6]), layer(y, [5, 6]))  # seeded: repeatable
    with torch.no_grad():
        layer.strength.fill_(5.0)
    strong = layer(torch.full((1, 3, 8, 8), 0.9))
    assert strong.min() == -1.0 and strong.max() == 1.0  # clamped to the output range, and both ends reached


def test_eval_grain_follows_the_input_and_differs_between_inputs_and_training_draws_vary():
    """An image translated alone or in a batch after others gets the same output (to float rounding); two inputs' grain (output minus
    the same network's output at strength 0) differ; training-mode calls draw anew; strength 0 is the plain U-Net."""
    x, z = levels(3, 3), torch.randn(3, 2)
    torch.manual_seed(0)
    plain = UNetGenerator(16, 8, 4, latent=2, dropout=0.0).eval()
    torch.manual_seed(0)
    grainy = UNetGenerator(16, 8, 4, latent=2, dropout=0.0, output_grain=True).eval()
    with torch.no_grad():
        assert torch.equal(grainy(x, z), plain(x, z))
        grainy.grain.strength.fill_(0.1)
        out = grainy(x, z)
        assert torch.allclose(grainy(x[2:], z[2:]), out[2:], atol=1e-5)  # a batch of one convolves in another order
        grain = out - plain(x, z)
        assert grain.abs().mean() > 0.02
        assert (grain[0] - grain[1]).abs().mean() > 0.02
        grainy.train()
        first, second = grainy(x, z), grainy(x, z)
    assert (first - second).abs().mean() > 0.02


def test_off_adds_no_settings_key_a_value_may_be_given_per_direction_and_resnet_refuses(default_params):
    from vtgen.io.params import ParamsError, validate_params

    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["output_grain"] is False
    assert "output_grain" not in objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    assert build_generator(dict(SETTINGS, size=32, ngf=8)).grain is None
    params["translation"]["class_gan"]["output_grain"] = {"v2t": True, "t2v": False}
    validate_params(params)
    v2t = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    assert isinstance(build_generator(dict(v2t, size=32, ngf=8)).grain, OutputGrain)
    assert "output_grain" not in objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    with pytest.raises(ValueError, match="output_grain is a U-Net setting"):
        build_generator(dict(v2t, size=32, ngf=8, generator="resnet"))
    params["translation"]["class_gan"]["output_grain"] = 1
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.output_grain"):
        validate_params(params)


def test_training_moves_the_strength_and_the_generator_file_keeps_it(tmp_path):
    torch.manual_seed(0)
    settings = fast_class_gan_settings(output_grain=True)
    training = TranslatorTraining(settings, "cpu", num_classes=2)
    for _ in range(2):
        training.step(*batch())
    assert training.generator.grain.strength.abs().sum() > 0  # learnt away from 0
    loaded = reloads_as_trained(training, settings, tmp_path)
    assert torch.equal(loaded.grain.strength, training.generator.grain.strength)
