"""class_gan.generator: resnet (Johnson et al. 2016; CycleGAN's and CUT's generator): shapes, borders, the encoder
PatchNCE reads, how it is built and rebuilt from a model file, and the class_gan step with it."""

from __future__ import annotations

import pytest
import torch

from vtgen.core.models import build_generator, ResnetGenerator, UNetGenerator
from vtgen.core.translator import TranslatorTraining

SETTINGS = {"size": 32, "ngf": 8, "ndf": 8, "kernel": 4, "discriminator": "patch", "patch_layers": 2,
            "gan_loss": "bce", "l1_weight": 100.0, "optimizer": "adam", "lr": 2e-4, "betas": [0.5, 0.999],
            "batch_size": 4, "iterations": 4, "objective": "class_gan", "r1": 0.1, "diffaugment": True,
            "mode_seeking": 1.0, "mode_seeking_pool": 1, "statistics": 0.0, "class_guidance": 0.0, "semantic": 0.0,
            "skips": None, "d_lr_ratio": 1.0, "latent": 8, "upsample": "transpose", "generator": "resnet"}


@pytest.mark.parametrize("size", [16, 32, 64])
def test_it_maps_an_image_and_its_code_to_an_image_of_the_same_side_in_range(size):
    torch.manual_seed(0)
    generator = ResnetGenerator(size, ngf=8, in_channels=5, latent=3).train()
    out = generator(torch.rand(2, 5, size, size) * 2 - 1)
    assert out.shape == (2, 3, size, size)
    assert out.abs().max() <= 1.0
    x, z = torch.rand(2, 5, size, size), torch.randn(2, 3)
    generator.eval()
    assert torch.equal(generator(x, z), generator(x, z))
    assert not torch.allclose(generator(x, z), generator(x, -z))  # the code reaches the output
    with pytest.raises(ValueError, match="expected a code of shape"):
        generator(x, torch.zeros(2, 4))
    with pytest.raises(ValueError, match=r"expected N x 5 x"):
        generator(torch.rand(2, 3, size, size))


def test_a_constant_input_gives_a_constant_output_to_the_border():
    """Reflection padding and no 1x1 bottleneck: a flat input stays flat at every pixel, borders included. The
    U-Net's zero padding does not (its outputs on class pairs were dark-framed blobs)."""
    torch.manual_seed(0)
    resnet, unet = ResnetGenerator(32, ngf=8).eval(), UNetGenerator(32, 8, 4).eval()
    flat = torch.full((1, 3, 32, 32), 0.3)
    with torch.no_grad():
        assert resnet(flat).std(dim=(-2, -1)).max() < 1e-5
        assert unet(flat).std(dim=(-2, -1)).min() > 1e-4


def test_encode_gives_three_levels_and_leaves_the_running_statistics_alone():
    torch.manual_seed(0)
    generator = ResnetGenerator(32, ngf=8, latent=2).train()
    before = {k: v.clone() for k, v in generator.state_dict().items()}
    x = torch.rand(4, 3, 32, 32)
    features = generator.encode(x, (0, 1, 2))
    assert [tuple(f.shape) for f in features] == [(4, 8, 32, 32), (4, 16, 16, 16), (4, 32, 8, 8)]
    assert [generator.feature_width(level) for level in range(generator.feature_levels)] == [8, 16, 32]
    after = generator.state_dict()
    assert all(torch.equal(before[k], after[k]) for k in before)
    manual = torch.cat([x, torch.zeros(4, 2, 32, 32)], dim=1)
    for level, block in enumerate(generator.encoder):
        manual = block(manual)
        assert torch.allclose(features[level], manual)


def test_build_generator_names_the_kind_and_refuses_unet_settings_for_the_resnet():
    torch.manual_seed(0)
    built = build_generator(dict(SETTINGS, generator="unet"))
    torch.manual_seed(0)
    direct = UNetGenerator(32, 8, 4, latent=8)
    assert type(built) is UNetGenerator
    assert all(torch.equal(a, b) for a, b in zip(built.state_dict().values(), direct.state_dict().values()))
    assert type(build_generator({k: v for k, v in SETTINGS.items() if k != "generator"})) is UNetGenerator
    assert type(build_generator(SETTINGS)) is ResnetGenerator
    with pytest.raises(ValueError, match="class_gan.skips"):
        build_generator(dict(SETTINGS, skips=2))
    with pytest.raises(ValueError, match="unknown generator"):
        build_generator(dict(SETTINGS, generator="vit"))


def batch(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(4, 3, 32, 32, generator=g) * 2 - 1, torch.rand(4, 3, 32, 32, generator=g) * 2 - 1,
            torch.tensor([0, 0, 1, 1]))


def test_the_class_gan_step_trains_it_with_patchnce_and_a_model_file_rebuilds_it(tmp_path):
    from vtgen.io.checkpoints import load_translator, save_generator
    from vtgen.stages.generate import translate

    settings = dict(SETTINGS, nce=0.5)
    torch.manual_seed(0)
    training = TranslatorTraining(settings, "cpu", num_classes=2)
    assert isinstance(training.generator, ResnetGenerator)
    assert training.nce_levels == (0, 1, 2)
    start = {k: v.clone() for k, v in training.generator.state_dict().items()}
    for step in range(3):
        losses = training.step(*batch(step))
        assert all(torch.isfinite(v) for v in losses.values())
    assert any(not torch.equal(start[k], v) for k, v in training.generator.state_dict().items())
    save_generator(tmp_path / "generator.pt", training.generator, settings, "v2t", "all")
    loaded, _ = load_translator(tmp_path)
    assert isinstance(loaded, ResnetGenerator)
    images = torch.randint(0, 256, (4, 3, 32, 32), dtype=torch.uint8)
    assert torch.equal(translate(loaded, images, seed=3), translate(training.generator.eval(), images, seed=3))
