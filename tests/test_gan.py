"""Pure GAN pieces: pixel scaling, the paper's random positioning, losses, optimisers."""

import math

import pytest
import torch

from vtgen.core.gan import adversarial_loss, make_optimizer, noise_margin, random_positioning, to_model_range, to_uint8


def test_pixel_scaling_round_trips_every_uint8_value():
    values = torch.arange(256, dtype=torch.uint8).view(1, 1, 16, 16)
    scaled = to_model_range(values)
    assert scaled.min() == -1 and scaled.max() == 1
    assert torch.equal(to_uint8(scaled), values)
    assert torch.equal(to_uint8(torch.tensor([-3.0, 3.0])), torch.tensor([0, 255], dtype=torch.uint8))


def test_noise_margin_is_the_papers_30_pixels_at_256_and_scales():
    assert noise_margin(256) == 30
    assert noise_margin(64) == 8 and noise_margin(512) == 60


def test_random_positioning_moves_input_and_target_together():
    torch.manual_seed(0)
    images = torch.rand(6, 3, 32, 32) * 2 - 1
    x, y = random_positioning(images, images.clone(), torch.Generator().manual_seed(1))
    assert x.shape == y.shape == images.shape
    assert torch.equal(x, y)  # an aligned pair stays aligned
    again, _ = random_positioning(images, images.clone(), torch.Generator().manual_seed(1))
    other, _ = random_positioning(images, images.clone(), torch.Generator().manual_seed(2))
    assert torch.equal(x, again) and not torch.equal(x, other)
    assert not torch.allclose(x, images)  # the crop really moves the content
    assert x.min() >= -1 and x.max() <= 1  # bilinear resampling stays in range


@pytest.mark.parametrize("kind", ["bce", "lsgan"])
def test_adversarial_losses_have_their_textbook_values(kind):
    zero = torch.zeros(4, 1)
    if kind == "bce":
        assert adversarial_loss(zero, True, kind).item() == pytest.approx(math.log(2))
        assert adversarial_loss(torch.full((4, 1), 3.0), False, kind).item() == pytest.approx(math.log1p(math.exp(3)))
    else:
        assert adversarial_loss(zero, True, kind).item() == pytest.approx(1.0)
        assert adversarial_loss(zero, False, kind).item() == pytest.approx(0.0)


def test_bce_on_logits_is_stable_at_extreme_logits():
    huge = torch.tensor([[1e4], [-1e4]])
    assert adversarial_loss(huge, True).item() == pytest.approx(5e3)  # mean of 0 and 1e4
    assert math.isfinite(adversarial_loss(huge.to(torch.bfloat16), False).item())
    assert adversarial_loss(torch.tensor([[1e4]]), True).item() == 0.0


def test_unknown_loss_and_optimizer_are_refused():
    with pytest.raises(ValueError, match="unknown gan_loss 'hinge'"):
        adversarial_loss(torch.zeros(1, 1), True, "hinge")
    with pytest.raises(ValueError, match="unknown optimizer 'sgd'"):
        make_optimizer([torch.zeros(1, requires_grad=True)], "sgd", 1e-3, (0.5, 0.999))


def test_optimizers_carry_the_configured_settings():
    weights = [torch.zeros(1, requires_grad=True)]
    adam = make_optimizer(weights, "adam", 2e-4, [0.5, 0.999])
    assert isinstance(adam, torch.optim.Adam) and adam.defaults["betas"] == (0.5, 0.999) and adam.defaults["lr"] == 2e-4
    rmsprop = make_optimizer(weights, "rmsprop", 2e-4, [0.5, 0.999])
    assert isinstance(rmsprop, torch.optim.RMSprop) and rmsprop.defaults["alpha"] == 0.9


@pytest.mark.parametrize("name", ["adam", "rmsprop"])
def test_the_multi_tensor_step_matches_the_default_step_to_rounding(name):
    torch.manual_seed(0)
    start = [torch.randn(5, 3), torch.randn(7)]
    plain_w, fast_w = ([w.clone().requires_grad_() for w in start] for _ in range(2))
    plain = make_optimizer(plain_w, name, 1e-2, [0.5, 0.999])
    fast = make_optimizer(fast_w, name, 1e-2, [0.5, 0.999], multi_tensor_on="cpu")
    assert (fast.defaults["fused"] if name == "adam" else fast.defaults["foreach"]) is True
    assert not plain.defaults.get("fused") and not plain.defaults["foreach"]
    for step in range(3):
        for weights, optimizer in ((plain_w, plain), (fast_w, fast)):
            optimizer.zero_grad()
            sum(((w - step) ** 2).sum() for w in weights).backward()
            optimizer.step()
    for a, b, s in zip(plain_w, fast_w, start):
        assert not torch.equal(a, s)  # the weights moved ...
        assert torch.allclose(a, b, rtol=1e-5, atol=1e-7)  # ... the same way
    mps = make_optimizer([torch.zeros(1, requires_grad=True)], "adam", 1e-3, [0.5, 0.999], multi_tensor_on="mps")
    assert not mps.defaults["fused"]  # fused Adam exists for CPU and CUDA only: the default step elsewhere
