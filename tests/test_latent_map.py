"""class_gan.latent_map: the latent code drawn per pixel (noise maps) instead of once per image (its shapes, that
it reaches the output place by place, its off switch, per-direction values, and a generator file that keeps it)."""

from __future__ import annotations

import copy

import pytest
import torch

from test_class_gan import CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.models import build_generator, fixed_codes, ResnetGenerator, UNetGenerator
from vtgen.io.checkpoints import load_translator, save_generator
from vtgen.stages.train import objective_settings, train_translator


@pytest.mark.parametrize("make", [lambda: UNetGenerator(32, 8, 4, latent=3, upsample="resize", latent_map=True),
                                  lambda: ResnetGenerator(32, 8, latent=3, latent_map=True)])
def test_a_map_code_has_one_value_per_pixel_and_changes_the_output_where_it_changes(make):
    torch.manual_seed(0)
    generator = make().eval()
    codes = fixed_codes(generator, 2, seed=5)
    assert codes.shape == (2, 3, 32, 32)
    assert torch.equal(codes, fixed_codes(generator, 2, seed=5))  # a seed repeats it
    x = torch.rand(1, 3, 32, 32) * 2 - 1
    with torch.no_grad():
        base = generator(x, codes[:1])
        again = generator(x, codes[:1])
        other = generator(x, codes[1:])
    assert torch.equal(base, again)
    assert (base - other).abs().mean() > 1e-3
    # a code that differs only in the bottom-right corner moves the output more there than in the far corner
    local = codes[:1].clone()
    local[..., 24:, 24:] = codes[1:, :, 24:, 24:]
    with torch.no_grad():
        moved = (generator(x, local) - base).abs().mean(dim=(0, 1))
    assert moved[24:, 24:].mean() > 2 * moved[:8, :8].mean()
    with pytest.raises(ValueError, match=r"expected a code of shape \(1, 3, 32, 32\)"):
        generator(x, torch.zeros(1, 3))  # a per-image code is refused by a map generator


def test_off_adds_no_settings_key_and_a_value_may_be_given_per_direction(default_params):
    from vtgen.io.params import ParamsError, validate_params
    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["latent_map"] is False
    plain = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    plain_t2v = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")  # the defaults differ by direction
    assert "latent_map" not in plain  # so the default's checkpoint keys are those of the code before the switch
    assert build_generator(dict(plain, size=32, ngf=8)).latent_map is False
    params["translation"]["class_gan"]["latent_map"] = {"v2t": True, "t2v": False}
    validate_params(params)
    v2t = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    assert v2t["latent_map"] is True and build_generator(dict(v2t, size=32, ngf=8)).latent_map is True
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v") == plain_t2v
    params["translation"]["class_gan"]["latent_map"] = "yes"
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.latent_map"):
        validate_params(params)


def test_training_with_a_map_code_gives_a_generator_whose_outputs_vary_with_the_map(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=3, latent_map=True)
    run = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=3, resume=False, log_every=1, seed=0)
    trained = train_translator(data, settings, run, "v2t", "all", checkpoint_dir=tmp_path, progress=False)
    generator = trained.generator.eval()
    assert generator.latent_map and generator.encoder[0][0].in_channels == 3 + CLASS_GAN["latent"]
    codes = fixed_codes(generator, 2, seed=1)
    x = data.inputs[:1].float() / 127.5 - 1
    with torch.no_grad():
        assert (generator(x, codes[:1]) - generator(x, codes[1:])).abs().mean() > 1e-3
    # the generator file rebuilds a map generator that computes the same image
    save_generator(tmp_path / "generator.pt", generator, settings, "v2t", "all")
    loaded, _ = load_translator(tmp_path / "generator.pt")
    assert loaded.latent_map
    with torch.no_grad():
        assert torch.equal(loaded(x, codes[:1]), generator(x, codes[:1]))
