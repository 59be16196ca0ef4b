"""Tests of the conditional GAN networks: shapes, parameter counts, skips, dropout, training, errors."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from vtgen.core.models import build_discriminator, conditional_pair, count_parameters, GlobalDiscriminator, PatchDiscriminator, unet_depth, UNetGenerator


def rand_images(n: int, size: int, channels: int = 3, seed: int = 0) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.rand(n, channels, size, size, generator=generator) * 2 - 1


# ---------------------------------------------------------------------------------------------
# Independent closed-form parameter counts, written from the architecture description.

def conv_params(cin: int, cout: int, k: int, bias: bool, batchnorm: bool) -> int:
    return cin * cout * k * k + (cout if bias else 0) + (2 * cout if batchnorm else 0)


def expected_unet_params(size: int, ngf: int, k: int, cin: int = 3, cout: int = 3) -> int:
    depth = size.bit_length() - 1
    width = [ngf * min(2**i, 8) for i in range(depth)]
    total = conv_params(cin, width[0], k, bias=True, batchnorm=False)  # outermost encoder
    for i in range(1, depth - 1):
        total += conv_params(width[i - 1], width[i], k, bias=False, batchnorm=True)
    total += conv_params(width[depth - 2], width[depth - 1], k, bias=True, batchnorm=False)  # innermost
    # decoder: level 0 reads the bottleneck, later levels read [previous output, skip] of equal widths
    total += conv_params(width[depth - 1], width[depth - 2], k, bias=False, batchnorm=True)
    for j in range(1, depth - 1):
        total += conv_params(2 * width[depth - 1 - j], width[depth - 2 - j], k, bias=False, batchnorm=True)
    total += conv_params(2 * width[0], cout, k, bias=True, batchnorm=False)  # outermost decoder
    return total


def expected_global_params(size: int, ndf: int, k: int, cin: int = 6) -> int:
    total = conv_params(cin, ndf, k, bias=True, batchnorm=False)
    for cin_, cout_ in [(ndf, 2 * ndf), (2 * ndf, 4 * ndf), (4 * ndf, 8 * ndf)]:
        total += conv_params(cin_, cout_, k, bias=False, batchnorm=True)
    return total + 8 * ndf * (size // 16) ** 2 + 1


def expected_patch_params(ndf: int, layers: int, k: int, cin: int = 6) -> int:
    total = conv_params(cin, ndf, k, bias=True, batchnorm=False)
    previous = ndf
    for n in range(1, layers + 1):  # n == layers is the stride-1 conv
        width = ndf * min(2**n, 8)
        total += conv_params(previous, width, k, bias=False, batchnorm=True)
        previous = width
    return total + conv_params(previous, 1, k, bias=True, batchnorm=False)


# ---------------------------------------------------------------------------------------------
# Generator


@pytest.mark.parametrize("size", [16, 32, 64, 128, 256])
@pytest.mark.parametrize("kernel", [4, 5])
def test_generator_output_shape_and_range(size, kernel):
    net = UNetGenerator(size, ngf=4, kernel=kernel)
    out = net(rand_images(2, size))
    assert out.shape == (2, 3, size, size)
    assert torch.isfinite(out).all()
    assert out.min() >= -1 and out.max() <= 1


@pytest.mark.parametrize("size, depth", [(16, 4), (32, 5), (64, 6), (128, 7), (256, 8)])
def test_unet_depth(size, depth):
    assert unet_depth(size) == depth
    net = UNetGenerator(size, ngf=2)
    assert net.depth == depth and net.size == size
    assert len(net.encoder) == len(net.decoder) == depth


def test_generator_keeps_only_the_deepest_skips():
    """skips = k: the k skip connections nearest the bottleneck stay; an input change confined to fine detail
    that the encoder's first level sees reaches the output only through the kept ones."""
    torch.manual_seed(0)
    full = UNetGenerator(32, ngf=4)
    torch.manual_seed(0)
    same = UNetGenerator(32, ngf=4, skips=4)  # 32 px: depth 5, 4 skips = all
    assert all(torch.equal(a, b) for a, b in zip(full.state_dict().values(), same.state_dict().values()))
    for k in range(5):
        net = UNetGenerator(32, ngf=4, skips=k).eval()
        joined = [level for level in range(1, 5)
                  if net.decoder[level][0].in_channels == 2 * net.encoder[4 - level][0].out_channels]
        assert joined == list(range(1, k + 1))
        assert net(rand_images(2, 32)).shape == (2, 3, 32, 32)
    # with no skips, the output is a function of the 1x1 bottleneck alone
    net = UNetGenerator(32, ngf=4, skips=0).eval()
    x = rand_images(1, 32)
    bottleneck = x
    for block in net.encoder:
        bottleneck = block(bottleneck)
    assert torch.equal(net(x), net.decoder[4](net.decoder[3](net.decoder[2](net.decoder[1](net.decoder[0](bottleneck))))))
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="skips"):
            UNetGenerator(32, ngf=4, skips=bad)


def test_generator_bottleneck_is_one_by_one():
    net = UNetGenerator(64, ngf=4, kernel=5)
    x = rand_images(2, 64)
    sides = []
    for block in net.encoder:
        x = block(x)
        sides.append(x.shape[-1])
    assert sides == [32, 16, 8, 4, 2, 1]


@pytest.mark.parametrize(
    "size, ngf, kernel", [(16, 2, 4), (32, 8, 5), (64, 32, 4), (128, 4, 5), (256, 4, 4), (256, 8, 5)]
)
def test_generator_parameter_count_matches_closed_form(size, ngf, kernel):
    assert count_parameters(UNetGenerator(size, ngf=ngf, kernel=kernel)) == expected_unet_params(size, ngf, kernel)


def test_generator_parameter_count_by_hand():
    # size 16 -> depth 4, ngf 2 -> encoder widths 2, 4, 8, 16; kernel 4 -> 16 weights per channel pair.
    # encoder: 3*2*16+2 = 98 | 2*4*16+2*4 = 136 | 4*8*16+2*8 = 528 | 8*16*16+16 = 2064   -> 2826
    # decoder: 16*8*16+2*8 = 2064 | (8+8)*4*16+2*4 = 1032 | (4+4)*2*16+2*2 = 260 | (2+2)*3*16+3 = 195 -> 3551
    assert count_parameters(UNetGenerator(16, ngf=2, kernel=4)) == 2826 + 3551 == 6377


def test_count_parameters_ignores_frozen_parameters():
    net = UNetGenerator(16, ngf=2)
    total = count_parameters(net)
    for p in net.encoder[0].parameters():
        p.requires_grad_(False)
    assert count_parameters(net) == total - (3 * 2 * 16 + 2)


def test_generator_skip_connections_widen_decoder_inputs():
    net = UNetGenerator(64, ngf=8, kernel=4)  # encoder widths 8, 16, 32, 64, 64, 64
    enc_widths = [block[0].out_channels for block in net.encoder]
    assert enc_widths == [8, 16, 32, 64, 64, 64]
    dec_convs = [block[0] for block in net.decoder]
    assert all(isinstance(conv, nn.ConvTranspose2d) for conv in dec_convs)
    assert dec_convs[0].in_channels == 64  # bottleneck only
    assert [c.in_channels for c in dec_convs[1:]] == [64 + 64, 64 + 64, 32 + 32, 16 + 16, 8 + 8]
    assert [c.out_channels for c in dec_convs] == [64, 64, 32, 16, 8, 3]


def test_generator_output_depends_on_skip_path():
    # Zeroing the bottleneck's output cannot stop the input from reaching the output via the skips.
    torch.manual_seed(0)
    net = UNetGenerator(32, ngf=4).eval()
    with torch.no_grad():
        net.encoder[-1][0].weight.zero_()
        a, b = rand_images(1, 32, seed=1), rand_images(1, 32, seed=2)
        assert not torch.allclose(net(a), net(b))


def test_generator_block_structure():
    net = UNetGenerator(64, ngf=4)
    kinds = lambda block: [type(m) for m in block]  # noqa: E731
    assert kinds(net.encoder[0]) == [nn.Conv2d, nn.LeakyReLU]
    assert net.encoder[0][0].bias is not None
    assert kinds(net.encoder[1]) == [nn.Conv2d, nn.BatchNorm2d, nn.LeakyReLU]
    assert net.encoder[1][0].bias is None
    assert kinds(net.encoder[-1]) == [nn.Conv2d, nn.ReLU]
    assert net.encoder[-1][0].bias is not None
    assert kinds(net.decoder[-1]) == [nn.ConvTranspose2d, nn.Tanh]
    assert net.decoder[-1][0].bias is not None
    assert kinds(net.decoder[3]) == [nn.ConvTranspose2d, nn.BatchNorm2d, nn.ReLU]


def test_weight_initialisation():
    torch.manual_seed(0)
    net = UNetGenerator(128, ngf=16)
    conv_weights = torch.cat([m.weight.flatten() for m in net.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))])
    assert abs(conv_weights.mean().item()) < 2e-3
    assert conv_weights.std().item() == pytest.approx(0.02, rel=0.05)
    bn_weights = torch.cat([m.weight for m in net.modules() if isinstance(m, nn.BatchNorm2d)])
    assert bn_weights.mean().item() == pytest.approx(1.0, abs=0.01)
    biases = [m.bias for m in net.modules() if getattr(m, "bias", None) is not None]
    assert biases and all(torch.count_nonzero(b) == 0 for b in biases)


@pytest.mark.parametrize("size, levels", [(16, [0, 1]), (32, [0, 1, 2]), (64, [0, 1, 2]), (256, [0, 1, 2])])
def test_dropout_only_on_inner_decoder_levels(size, levels):
    net = UNetGenerator(size, ngf=2, dropout=0.5)
    with_dropout = [j for j, block in enumerate(net.decoder) if any(isinstance(m, nn.Dropout) for m in block)]
    assert with_dropout == levels
    assert not any(isinstance(m, nn.Dropout) for m in net.encoder.modules())
    assert net.decoder[levels[0]][-1].p == 0.5


def test_dropout_active_in_train_mode_only():
    torch.manual_seed(0)
    net = UNetGenerator(32, ngf=8, dropout=0.5)
    x = rand_images(4, 32)
    with torch.no_grad():
        net.train()
        torch.manual_seed(1)
        first = net(x)
        torch.manual_seed(2)
        second = net(x)
        torch.manual_seed(1)
        repeat = net(x)
        assert not torch.allclose(first, second)
        assert torch.equal(first, repeat)  # the variation comes from the RNG
        net.eval()
        torch.manual_seed(1)
        a = net(x)
        torch.manual_seed(2)
        b = net(x)
        assert torch.equal(a, b)


def test_no_dropout_means_deterministic_training_forward():
    net = UNetGenerator(32, ngf=8, dropout=0.0).train()
    assert not any(isinstance(m, nn.Dropout) for m in net.modules())
    x = rand_images(4, 32)
    with torch.no_grad():
        torch.manual_seed(1)
        a = net(x)
        torch.manual_seed(2)
        b = net(x)
    assert torch.equal(a, b)


# ---------------------------------------------------------------------------------------------
# Discriminators


@pytest.mark.parametrize("size, kernel", [(16, 5), (32, 4), (64, 5), (256, 5)])
def test_global_discriminator_output(size, kernel):
    net = GlobalDiscriminator(size, ndf=4, kernel=kernel)
    out = net(conditional_pair(rand_images(3, size), rand_images(3, size, seed=1)))
    assert out.shape == (3, 1)
    assert torch.isfinite(out).all()
    assert net.classifier.in_features == 8 * 4 * (size // 16) ** 2


@pytest.mark.parametrize("size, ndf, kernel", [(16, 4, 5), (64, 8, 4), (256, 16, 5), (256, 64, 5)])
def test_global_discriminator_parameter_count(size, ndf, kernel):
    assert count_parameters(GlobalDiscriminator(size, ndf=ndf, kernel=kernel)) == expected_global_params(size, ndf, kernel)


@pytest.mark.parametrize("ndf, layers, kernel", [(4, 1, 4), (8, 2, 5), (32, 3, 4), (64, 3, 4), (8, 4, 5)])
def test_patch_discriminator_parameter_count(ndf, layers, kernel):
    assert count_parameters(PatchDiscriminator(ndf, layers, kernel)) == expected_patch_params(ndf, layers, kernel)


@pytest.mark.parametrize(
    "size, layers, kernel, side",
    [(64, 3, 4, 6), (32, 2, 4, 6), (64, 3, 5, 8), (32, 2, 5, 8), (256, 3, 4, 30), (16, 1, 4, 6)],
)
def test_patch_discriminator_map_shape(size, layers, kernel, side):
    # kernel 4 (pix2pix): 64 -> 32 -> 16 -> 8 -> 7 -> 6; kernel 5 keeps the side in the stride-1 convs.
    net = PatchDiscriminator(ndf=4, layers=layers, kernel=kernel)
    out = net(conditional_pair(rand_images(2, size), rand_images(2, size, seed=1)))
    assert out.shape == (2, 1, side, side)
    assert net.output_side(size) == side
    assert torch.isfinite(out).all()


def test_build_discriminator():
    glob = build_discriminator("global", 32, 4, 5, 3)
    assert isinstance(glob, GlobalDiscriminator) and glob.size == 32
    patch = build_discriminator("patch", 32, 4, 4, 2)
    assert isinstance(patch, PatchDiscriminator) and patch.layers == 2
    with pytest.raises(ValueError, match=r"unknown discriminator kind 'pixel'.*global, patch"):
        build_discriminator("pixel", 32, 4, 4, 2)
    with pytest.raises(ValueError, match=r"size 16 is too small for patch_layers=4"):
        build_discriminator("patch", 16, 4, 4, 4)


def test_conditional_pair_stacks_channels():
    condition, image = rand_images(2, 16), rand_images(2, 16, seed=1)
    pair = conditional_pair(condition, image)
    assert pair.shape == (2, 6, 16, 16)
    assert torch.equal(pair[:, :3], condition) and torch.equal(pair[:, 3:], image)


@pytest.mark.parametrize("kind", ["global", "patch"])
def test_discriminator_learns_toy_task(kind):
    # real: the condition paired with itself; fake: the condition paired with noise.
    torch.manual_seed(0)
    size = 32
    net = build_discriminator(kind, size, ndf=8, kernel=4 if kind == "patch" else 5, patch_layers=2)
    optimiser = torch.optim.Adam(net.parameters(), lr=2e-3, betas=(0.5, 0.999))
    loss_fn = nn.BCEWithLogitsLoss()

    def loss_on(seed: int) -> torch.Tensor:
        # Real and fake share one batch: with train-mode BatchNorm, an all-real or all-fake batch is
        # normalised to the same statistics, which hides the very difference to be learnt.
        condition = rand_images(8, size, seed=seed)
        noise = rand_images(8, size, seed=seed + 1000)
        pairs = torch.cat([conditional_pair(condition, condition), conditional_pair(condition, noise)])
        logits = net(pairs)
        labels = torch.cat([torch.ones_like(logits[:8]), torch.zeros_like(logits[8:])])
        return loss_fn(logits, labels)

    with torch.no_grad():
        initial = loss_on(999).item()
    for step in range(30):
        optimiser.zero_grad()
        loss = loss_on(step)
        loss.backward()
        optimiser.step()
    with torch.no_grad():
        final = loss_on(999).item()
    assert final < 0.5 * initial, (initial, final)


# ---------------------------------------------------------------------------------------------
# Errors


def test_generator_rejects_wrong_input_shape():
    net = UNetGenerator(64, ngf=2)
    with pytest.raises(ValueError, match=r"expected N x 3 x 64 x 64 input, got shape \(1, 3, 32, 32\)"):
        net(torch.zeros(1, 3, 32, 32))
    with pytest.raises(ValueError, match=r"expected N x 3 x 64 x 64 input"):
        net(torch.zeros(1, 1, 64, 64))
    with pytest.raises(ValueError, match=r"expected N x 3 x 64 x 64 input"):
        net(torch.zeros(3, 64, 64))


def test_global_discriminator_rejects_wrong_input_shape():
    with pytest.raises(ValueError, match=r"expected N x 6 x 32 x 32 input"):
        GlobalDiscriminator(32, ndf=2)(torch.zeros(1, 6, 64, 64))


@pytest.mark.parametrize("size", [100, 8, 0, -16, 48, 16.0])
def test_bad_sizes_are_rejected(size):
    message = rf"size must be a power of two >= 16, got {size}"
    with pytest.raises(ValueError, match=message):
        unet_depth(size)
    with pytest.raises(ValueError, match=message):
        UNetGenerator(size)
    with pytest.raises(ValueError, match=message):
        GlobalDiscriminator(size)


@pytest.mark.parametrize("kernel", [3, 6, 2])
def test_bad_kernels_are_rejected(kernel):
    message = rf"kernel size must be one of \(4, 5\), got {kernel}"
    with pytest.raises(ValueError, match=message):
        UNetGenerator(32, kernel=kernel)
    with pytest.raises(ValueError, match=message):
        GlobalDiscriminator(32, kernel=kernel)
    with pytest.raises(ValueError, match=message):
        PatchDiscriminator(kernel=kernel)


def test_patch_discriminator_rejects_bad_layers_and_small_inputs():
    with pytest.raises(ValueError, match=r"layers must be an integer >= 1, got 0"):
        PatchDiscriminator(layers=0)
    net = PatchDiscriminator(ndf=2, layers=3, kernel=4)
    with pytest.raises(ValueError, match=r"input of size 16 x 16 is too small for layers=3"):
        net(torch.zeros(1, 6, 16, 16))
    with pytest.raises(ValueError, match=r"expected N x 6 x H x W input"):
        net(torch.zeros(1, 3, 64, 64))


def test_bad_dropout_is_rejected():
    with pytest.raises(ValueError, match=r"dropout must be in \[0, 1\), got 1.5"):
        UNetGenerator(32, dropout=1.5)


# ---------------------------------------------------------------------------------------------
# Precision and memory format


def all_networks(size: int):
    return [
        (UNetGenerator(size, ngf=4), 3, (2, 3, size, size)),
        (GlobalDiscriminator(size, ndf=4), 6, (2, 1)),
        (PatchDiscriminator(ndf=4, layers=2), 6, (2, 1, 6, 6)),
    ]


def test_bf16_autocast_on_cpu():
    for net, channels, shape in all_networks(32):
        x = rand_images(2, 32, channels=channels)
        with torch.no_grad(), torch.autocast(device_type="cpu", dtype=torch.bfloat16):
            out = net(x)
        assert out.shape == shape
        assert torch.isfinite(out.float()).all()


def test_bf16_autocast_backward_on_cpu():
    net = UNetGenerator(32, ngf=4)
    with torch.autocast(device_type="cpu", dtype=torch.bfloat16):
        out = net(rand_images(2, 32))
    out.float().mean().backward()
    grads = [p.grad for p in net.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


def test_channels_last_matches_contiguous():
    for net, channels, shape in all_networks(32):
        net.eval()
        x = rand_images(2, 32, channels=channels)
        with torch.no_grad():
            reference = net(x)
            net = net.to(memory_format=torch.channels_last)
            out = net(x.to(memory_format=torch.channels_last))
        assert out.shape == shape
        torch.testing.assert_close(out, reference, rtol=1e-4, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_networks_on_cuda():
    for net, channels, shape in all_networks(32):
        net = net.cuda()
        x = rand_images(2, 32, channels=channels).cuda()
        out = net(x)
        assert out.shape == shape and out.is_cuda and torch.isfinite(out).all()
        with torch.autocast(device_type="cuda", dtype=torch.bfloat16):
            assert torch.isfinite(net(x.to(memory_format=torch.channels_last)).float()).all()


@pytest.mark.parametrize("kind", ["unet", "resnet"])
def test_a_grey_output_generator_draws_one_channel_repeated(kind):
    from vtgen.core.models import build_generator

    settings = {"size": 32, "ngf": 8, "kernel": 4, "generator": kind, "latent": 4}
    torch.manual_seed(0)
    colour = build_generator(settings)
    torch.manual_seed(0)
    grey = build_generator(dict(settings, grey_output=True))
    x = rand_images(3, 32)
    made = grey(x, torch.zeros(3, 4))
    assert made.shape == (3, 3, 32, 32) and torch.equal(made[:, 0], made[:, 2]) and torch.equal(made[:, 1], made[:, 2])
    assert made.std() > 0
    # the same network but the last convolution, which makes one channel instead of three
    assert count_parameters(colour) - count_parameters(grey) == 2 * (count_parameters(colour.decoder[-1] if kind == "unet"
                                                                                       else colour.decoder[-2]) // 3)
    assert not torch.equal(colour(x, torch.zeros(3, 4))[:, 0], colour(x, torch.zeros(3, 4))[:, 1])


def test_grey_targets_needs_every_pixel_of_every_image_grey():
    from vtgen.core.models import grey_targets

    images = torch.randint(0, 256, (4, 1, 8, 8), dtype=torch.uint8).repeat(1, 3, 1, 1)
    assert grey_targets(images)
    images[3, 2, 7, 7] ^= 1
    assert not grey_targets(images)
    assert not grey_targets(images[:0])
