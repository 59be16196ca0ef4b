"""class_gan.decoder_noise: per-pixel noise maps with a learned strength added in the finest U-Net decoder levels
(StyleGAN's noise inputs): that it starts as the identity, which levels get it, that eval mode is repeatable and
training draws vary, its off switch and per-direction values, and a generator file that keeps it."""

from __future__ import annotations

import copy

import pytest
import torch

from test_class_gan import CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.models import build_generator, NoiseInjection, UNetGenerator
from vtgen.io.checkpoints import load_translator, save_generator
from vtgen.stages.train import objective_settings, train_translator


def noise_layers(generator: torch.nn.Module) -> list[NoiseInjection]:
    return [module for module in generator.modules() if isinstance(module, NoiseInjection)]


def test_noise_injection_starts_as_the_identity_and_adds_one_map_per_image_scaled_per_channel():
    layer = NoiseInjection(3).train()
    x = torch.randn(2, 3, 8, 8)
    assert torch.equal(layer(x), x)
    with torch.no_grad():
        layer.strength.copy_(torch.tensor([0.0, 1.0, 2.0]))
    added = layer(x) - x
    assert torch.equal(added[:, 0], torch.zeros(2, 8, 8))
    assert torch.allclose(added[:, 2], 2 * added[:, 1], atol=1e-6)  # one map, shared by the channels
    assert not torch.allclose(added[0, 1], added[1, 1])  # a map per image
    assert 0.7 < added[:, 1].std().item() < 1.3


def test_levels_get_noise_finest_first_a_larger_count_means_every_level_and_a_negative_one_is_refused():
    generator = UNetGenerator(32, 8, 4, decoder_noise=2)  # depth 5: decoder levels 0-3 below the output
    sides = []
    for level, block in enumerate(generator.decoder):
        if any(isinstance(m, NoiseInjection) for m in block):
            sides.append(2 ** (level + 1))
    assert sides == [8, 16]
    assert noise_layers(UNetGenerator(32, 8, 4)) == []
    assert len(noise_layers(UNetGenerator(16, 8, 4, decoder_noise=5))) == 3  # a 16 px model has three levels below its output
    with pytest.raises(ValueError, match=r"decoder_noise must be an integer >= 0"):
        UNetGenerator(32, 8, 4, decoder_noise=-1)


def test_at_zero_strength_the_outputs_are_those_without_the_layers():
    """Built from the same seed, a generator with noise layers (strength 0) gives the plain generator's outputs,
    in eval mode and in training mode (where its draws do not reach dropout: the finest level has none)."""
    x, z = torch.rand(4, 3, 32, 32) * 2 - 1, torch.randn(4, 2)
    torch.manual_seed(0)
    plain = UNetGenerator(32, 8, 4, latent=2)
    torch.manual_seed(0)
    noisy = UNetGenerator(32, 8, 4, latent=2, decoder_noise=1)
    with torch.no_grad():
        for mode in (False, True):
            plain.train(mode), noisy.train(mode)
            torch.manual_seed(1)
            a = plain(x, z)
            torch.manual_seed(1)
            b = noisy(x, z)
            assert torch.equal(a, b)


def test_with_strength_training_draws_vary_the_output_and_eval_mode_repeats_itself():
    """The same input and code give different images at each training-mode call (the noise is drawn anew) and
    the same images at each eval-mode call (a fixed draw), which differ from those at strength 0."""
    x, z = torch.rand(4, 3, 32, 32) * 2 - 1, torch.randn(4, 2)
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, latent=2, decoder_noise=2, dropout=0.0)
    with torch.no_grad():
        before = generator.eval()(x, z)
        for layer in noise_layers(generator):
            layer.strength.fill_(1.0)
        after = generator(x, z)
        assert torch.equal(after, generator(x, z))
        assert (after - before).abs().mean() > 0.05 * before.abs().mean()
        generator.train()
        first, second = generator(x, z), generator(x, z)
    assert (first - second).abs().mean() > 0.05 * first.abs().mean()


def test_eval_mode_gives_an_image_its_own_noise_whatever_its_batch_or_position():
    """In eval mode an input translated alone, or at another place in another batch, gives the same image; two
    different inputs at the same batch position get different maps (not one shared draw per position)."""
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, latent=2, decoder_noise=2, dropout=0.0).eval()
    layers = noise_layers(generator)
    x, z = torch.rand(4, 3, 32, 32) * 2 - 1, torch.randn(4, 2)
    maps = []
    for layer in layers:  # what each layer adds, per image
        layer.register_forward_hook(lambda module, args, out: maps.append(out - args[0]))
    with torch.no_grad():
        for layer in layers:
            layer.strength.fill_(1.0)
        batch = generator(x, z)
        alone = generator(x[2:3], z[2:3])
        swapped = generator(x[[2, 0]], z[[2, 0]])
        torch.testing.assert_close(alone[0], batch[2], atol=1e-5, rtol=0)
        torch.testing.assert_close(swapped[0], batch[2], atol=1e-5, rtol=0)
        torch.testing.assert_close(swapped[1], batch[0], atol=1e-5, rtol=0)
        maps.clear()
        generator(x[:1], z[:1]), generator(x[1:2], z[1:2])  # each at position 0 of its own batch
    finest_first, finest_second = maps[len(layers) - 1], maps[2 * len(layers) - 1]
    assert (finest_first[0, 0] - finest_second[0, 0]).abs().mean() > 0.5  # unit-variance maps, not the same draw


def test_zero_adds_no_settings_key_a_value_may_be_given_per_direction_and_resnet_refuses(default_params):
    from vtgen.io.params import ParamsError, validate_params
    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["decoder_noise"] == {"v2t": 0, "t2v": 3}  # T2V's since the Sixty-first round
    assert "decoder_noise" not in objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    params["translation"]["class_gan"]["decoder_noise"] = 0
    plain = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    assert "decoder_noise" not in plain  # the default's checkpoint keys stay those of the code before the switch
    assert noise_layers(build_generator(dict(plain, size=32, ngf=8))) == []
    params["translation"]["class_gan"]["decoder_noise"] = {"v2t": 0, "t2v": 2}
    validate_params(params)
    t2v = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    assert len(noise_layers(build_generator(dict(t2v, size=32, ngf=8)))) == 2
    assert "decoder_noise" not in objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    with pytest.raises(ValueError, match="decoder_noise is a U-Net setting"):
        build_generator(dict(t2v, size=32, ngf=8, generator="resnet"))
    params["translation"]["class_gan"]["decoder_noise"] = -1
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.decoder_noise"):
        validate_params(params)


def test_training_learns_a_strength_and_gives_a_generator_file_that_keeps_it(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=3, decoder_noise=2)
    run = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=3, resume=False, log_every=1, seed=0)
    trained = train_translator(data, settings, run, "v2t", "all", checkpoint_dir=tmp_path, progress=False)
    generator = trained.generator.eval()
    assert all(layer.strength.abs().sum() > 0 for layer in noise_layers(generator))  # learnt away from 0
    save_generator(tmp_path / "generator.pt", generator, settings, "v2t", "all")
    loaded, _ = load_translator(tmp_path / "generator.pt")
    assert len(noise_layers(loaded)) == 2
    x, z = data.inputs[:2].float() / 127.5 - 1, torch.randn(2, CLASS_GAN["latent"])
    with torch.no_grad():
        assert torch.equal(loaded(x, z), generator(x, z))
