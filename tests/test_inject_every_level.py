"""class_gan.inject_every_level: the condition's channels and z fed again to every U-Net encoder level (BicycleGAN's
add-to-all): that they reach the deep levels, its off switch, per-direction values, PatchNCE's encoder features
and a generator file that keeps it."""

from __future__ import annotations

import copy

import pytest
import torch

from test_class_gan import CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.models import build_generator, UNetGenerator
from vtgen.io.checkpoints import load_translator, save_generator
from vtgen.stages.train import objective_settings, train_translator


def class_maps(index: int, classes: int = 4, size: int = 32) -> torch.Tensor:
    maps = torch.zeros(1, classes, size, size)
    maps[:, index] = 1.0
    return maps


@pytest.mark.parametrize("inject", [0, 4])
def test_the_class_reaches_the_deep_levels_only_when_injected(inject):
    """With the first level's weights on the class maps zeroed, the class can reach the output only through the
    injection: without it two classes give the same image, with it they differ."""
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, in_channels=3 + 4, inject=inject).eval()
    with torch.no_grad():
        generator.encoder[0][0].weight[:, 3:] = 0.0
        image = torch.rand(1, 3, 32, 32) * 2 - 1
        a = generator(torch.cat([image, class_maps(0)], dim=1))
        b = generator(torch.cat([image, class_maps(2)], dim=1))
    gap = (a - b).abs().mean().item()
    assert (gap > 0.03 * a.abs().mean().item()) if inject else (gap == 0.0)  # untrained outputs are small
    if inject:
        assert generator.encoder[1][0].in_channels == generator.encoder[0][0].out_channels + 4


def test_off_adds_no_settings_key_and_a_value_may_be_given_per_direction(default_params):
    from vtgen.io.params import ParamsError, validate_params
    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["inject_every_level"] is False
    plain = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    assert "inject_every_level" not in plain  # the default's checkpoint keys stay those of the code before the switch
    assert build_generator(dict(plain, size=32, ngf=8), 3 + 4).inject == 0
    params["translation"]["class_gan"]["inject_every_level"] = {"v2t": False, "t2v": True}
    validate_params(params)
    t2v = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    # told the class (4 maps) with an 8-channel code: 12 channels enter every level
    assert build_generator(dict(t2v, size=32, ngf=8, latent=8), 3 + 4).inject == 12
    assert "inject_every_level" not in objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    with pytest.raises(ValueError, match="inject_every_level is a U-Net setting"):
        build_generator(dict(t2v, size=32, ngf=8, generator="resnet"), 3 + 4)
    params["translation"]["class_gan"]["inject_every_level"] = "yes"
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.inject_every_level"):
        validate_params(params)


def test_encoder_features_carry_the_injection_as_the_forward_pass_does():
    """PatchNCE's encoder features (encode, zero code) equal the forward pass's encoder outputs with a zero code."""
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, in_channels=3 + 4, latent=2, inject=6).eval()
    x = torch.cat([torch.rand(2, 3, 32, 32) * 2 - 1, class_maps(1).expand(2, -1, -1, -1)], dim=1)
    seen = []
    hooks = [generator.encoder[level].register_forward_hook(lambda m, i, o: seen.append(o)) for level in (0, 2)]
    with torch.no_grad():
        generator(x, torch.zeros(2, 2))
        encoded = generator.encode(x, (0, 2))
    for hook in hooks:
        hook.remove()
    assert all(torch.equal(a, b) for a, b in zip(encoded, seen))


def test_training_with_injection_gives_a_generator_file_that_keeps_it(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=3, inject_every_level=True)
    run = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=3, resume=False, log_every=1, seed=0)
    trained = train_translator(data, settings, run, "v2t", "all", checkpoint_dir=tmp_path, progress=False)
    generator = trained.generator.eval()
    assert generator.inject == CLASS_GAN["latent"]  # not told the class: z alone enters every level
    save_generator(tmp_path / "generator.pt", generator, settings, "v2t", "all")
    loaded, _ = load_translator(tmp_path / "generator.pt")
    assert loaded.inject == generator.inject
    x, z = data.inputs[:1].float() / 127.5 - 1, torch.randn(1, CLASS_GAN["latent"])
    with torch.no_grad():
        assert torch.equal(loaded(x, z), generator(x, z))
