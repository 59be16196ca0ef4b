"""Conditional GAN networks: a U-Net generator and two discriminators (pure torch).

Images are ``N x 3 x S x S`` tensors in ``[-1, 1]`` with ``S`` a power of two >= 16.
A discriminator sees the condition image and the (real or generated) image stacked on the
channel axis (:func:`conditional_pair`) and returns raw logits (no sigmoid), to be used with
``BCEWithLogitsLoss``.

* :class:`UNetGenerator` - pix2pix-style encoder/decoder with skip connections, down to 1x1.
* :class:`ResnetGenerator` - two stride-2 levels, residual blocks at a quarter of the side, reflection padding
  (Johnson et al. 2016; CycleGAN's and CUT's generator for unpaired translation).
* :class:`GlobalDiscriminator` - four stride-2 convs and one linear layer: one logit per image.
* :class:`PatchDiscriminator` - PatchGAN: a map of logits, one per overlapping patch.
* :class:`ProjectionDiscriminator` - for class-paired data: a PatchGAN told the class, not the condition image.

Every network is initialised with :func:`init_weights` (DCGAN/pix2pix convention).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.parametrizations import spectral_norm

ALLOWED_KERNELS = (4, 5)
DISCRIMINATOR_KINDS = ("global", "patch")
MIN_SIZE = 16


def check_size(size: int) -> int:
    """Return ``size`` if it is a power of two >= 16; raise ValueError otherwise."""
    if isinstance(size, bool) or not isinstance(size, int) or size < MIN_SIZE or size & (size - 1):
        raise ValueError(f"size must be a power of two >= {MIN_SIZE}, got {size!r}")
    return size


def check_kernel(kernel: int) -> int:
    """Return ``kernel`` if it is 4 or 5; raise ValueError otherwise."""
    if isinstance(kernel, bool) or kernel not in ALLOWED_KERNELS:
        raise ValueError(f"kernel size must be one of {ALLOWED_KERNELS}, got {kernel!r}")
    return kernel


def resampling_padding(kernel: int) -> tuple[int, int]:
    """``(padding, output_padding)`` making a stride-2 conv halve and a stride-2 transposed conv
    double an even spatial size exactly (the conv ignores ``output_padding``)."""
    check_kernel(kernel)
    return (1, 0) if kernel == 4 else (2, 1)


def downsampling_conv(in_channels: int, out_channels: int, kernel: int, bias: bool,
                      padding_mode: str = "zeros") -> nn.Conv2d:
    """Stride-2 convolution that maps ``H x W`` to ``H/2 x W/2`` for even sizes, padding with ``padding_mode``."""
    padding, _ = resampling_padding(kernel)
    return nn.Conv2d(in_channels, out_channels, kernel, stride=2, padding=padding, bias=bias, padding_mode=padding_mode)


def upsampling_conv(in_channels: int, out_channels: int, kernel: int, bias: bool) -> nn.ConvTranspose2d:
    """Stride-2 transposed convolution that maps ``H x W`` to ``2H x 2W``."""
    padding, output_padding = resampling_padding(kernel)
    return nn.ConvTranspose2d(
        in_channels, out_channels, kernel, stride=2, padding=padding, output_padding=output_padding, bias=bias
    )


def balanced_kernel(weight: torch.Tensor) -> torch.Tensor:
    """A stride-2 transposed convolution's kernel (``in x out x k x k``) with the sums of its four sub-pixel kernels made
    equal by the least-squares change. Output pixel ``o`` takes the taps ``t`` with ``t = o + padding`` (mod 2) per axis, so
    the taps split into four classes by (row, column) parity, one per output sub-pixel; each class's ``c_q`` taps move by
    ``(s - S_q) / c_q``, ``S_q`` their sum and ``s = sum(S_q / c_q) / sum(1 / c_q)``. Equal sums make a constant input give
    a constant output away from the border: no checkerboard (the linear multirate condition Sugawara et al. 2019 carry to
    CNNs, meeting it by a zero-order hold, i.e. a resize convolution: 9 free taps of a 4 x 4 kernel; this keeps 13)."""
    size = weight.shape[-1]
    parity = torch.arange(size, device=weight.device) % 2
    classes = (2 * parity[:, None] + parity[None, :]).flatten()
    masks = (classes[None, :] == torch.arange(4, device=weight.device)[:, None]).to(weight.dtype)  # 4 x k*k
    counts = masks.sum(dim=1)
    sums = weight.flatten(2) @ masks.T  # in x out x 4
    target = (sums / counts).sum(dim=-1, keepdim=True) / (1 / counts).sum()
    return weight + (((target - sums) / counts) @ masks).view_as(weight)


REPLICATE_ABOVE = 2  # input side (px) above which BalancedTransposedConv pads by replication, as the encoder's reflect


class BalancedTransposedConv(nn.ConvTranspose2d):
    """A stride-2 transposed convolution that uses :func:`balanced_kernel` of its weight and, where its input is larger
    than :data:`REPLICATE_ABOVE` px, pads the input by one replicated pixel (cropping the two output pixels that adds per
    side), so that a constant input gives a constant output up to the border too: the freedom of pix2pix's upsampling
    to draw sub-pixel detail that varies with its input, without the checkerboard (the lattice V2T drew on flat fields,
    benchmarks/README.md, Sixty-seventh round) or the frame where the border pixels miss taps. Smaller inputs (the
    deepest levels, fed by the 1 x 1 bottleneck) keep the zero border: replicated, a 1 x 1 map could only give a
    constant one. For V2T on vt60_subset this rule measured no better than replicating everywhere: no lattice and no
    frame, but no grain and lower coverage than the transposed default (Sixty-eighth round). Under bf16 autocast the
    sums are equal to bf16 rounding."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        kernel = balanced_kernel(self.weight)
        if min(x.shape[-2:]) <= REPLICATE_ABOVE:
            return F.conv_transpose2d(x, kernel, self.bias, self.stride, self.padding, self.output_padding, self.groups,
                                      self.dilation)
        out = F.conv_transpose2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), kernel, self.bias,
                                 self.stride, self.padding, self.output_padding, self.groups, self.dilation)
        return out[..., 2:-2, 2:-2]


def balanced_upsampling_conv(in_channels: int, out_channels: int, kernel: int, bias: bool) -> BalancedTransposedConv:
    """:func:`upsampling_conv` with balanced sub-pixel kernels (:class:`BalancedTransposedConv`)."""
    padding, output_padding = resampling_padding(kernel)
    return BalancedTransposedConv(
        in_channels, out_channels, kernel, stride=2, padding=padding, output_padding=output_padding, bias=bias
    )


UPSAMPLINGS = ("transpose", "resize", "bilinear", "subpixel", "balanced")
PADDINGS = ("zeros", "reflect")  # the U-Net encoder's: pix2pix's zeros, or by reflection


def resize_conv(in_channels: int, out_channels: int, bias: bool) -> nn.Sequential:
    """Nearest-neighbour 2x upsampling, then a 3x3 convolution: ``H x W`` to ``2H x 2W`` without the
    uneven kernel overlap that gives a stride-2 transposed convolution its checkerboard (Odena et al. 2016).
    The convolution pads by reflection: zero padding gave the generator a border it drew saturated bands
    along (benchmarks/README.md, Tenth and Eleventh rounds)."""
    return nn.Sequential(nn.Upsample(scale_factor=2, mode="nearest"),
                         nn.Conv2d(in_channels, out_channels, 3, padding=1, padding_mode="reflect", bias=bias))


def bilinear_conv(in_channels: int, out_channels: int, bias: bool) -> nn.Sequential:
    """Bilinear 2x upsampling (half-pixel centres), then a 3x3 convolution padded by reflection: ``H x W`` to
    ``2H x 2W``. The bilinear step equals nearest-neighbour 2x followed by :class:`BinomialBlur` ([1, 3, 3, 1]/4 =
    [1, 1] * [1, 2, 1]/4 per axis), so unlike :func:`resize_conv` it leaves no 2 x 2 blocks whose edges, stacked over
    the decoder's levels, line up along the rows and columns (the plaid of benchmarks/README.md, Fifty-ninth round)."""
    return nn.Sequential(nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
                         nn.Conv2d(in_channels, out_channels, 3, padding=1, padding_mode="reflect", bias=bias))


class SubpixelConv(nn.Module):
    """A 3x3 convolution to 4 x ``out_channels`` maps, then ``PixelShuffle(2)``: ``H x W`` to ``2H x 2W`` (ESPCN, Shi et
    al. 2016). :func:`init_weights` gives it ICNR's start (Aitken et al. 2017): the four sub-pixel kernels of each output
    channel equal, so it begins as a convolution followed by nearest-neighbour upsampling, with no checkerboard, and
    may learn sub-pixel detail from there. Pads by replication (the bottleneck's map is 1 x 1, too small to reflect)."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool):
        super().__init__()
        self.conv = nn.Conv2d(in_channels, 4 * out_channels, 3, padding=1, padding_mode="replicate", bias=bias)
        self.shuffle = nn.PixelShuffle(2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.shuffle(self.conv(x))


def init_weights(module: nn.Module) -> None:
    """DCGAN/pix2pix initialisation of one module (use with ``net.apply(init_weights)``):
    conv and transposed-conv weights ~ N(0, 0.02), BatchNorm weights ~ N(1, 0.02), their biases 0; a
    :class:`SubpixelConv` draws one kernel per output channel and repeats it over its four sub-pixels (ICNR).
    Other modules (e.g. ``nn.Linear``) keep PyTorch's default initialisation."""
    if isinstance(module, SubpixelConv):
        conv = module.conv
        with torch.no_grad():
            kernel = torch.empty(conv.out_channels // 4, *conv.weight.shape[1:]).normal_(0.0, 0.02)
            conv.weight.copy_(kernel.repeat_interleave(4, dim=0))
            if conv.bias is not None:
                conv.bias.zero_()
    elif isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
        nn.init.normal_(module.weight, 0.0, 0.02)
        if module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.BatchNorm2d):
        nn.init.normal_(module.weight, 1.0, 0.02)
        nn.init.zeros_(module.bias)


def unet_depth(size: int) -> int:
    """Number of stride-2 levels taking ``size`` down to 1x1, i.e. ``log2(size)``."""
    return check_size(size).bit_length() - 1


def encoder_width(level: int, base_width: int) -> int:
    """Channel width at encoder level ``level`` (0-based): ``base_width * min(2**level, 8)``."""
    return base_width * min(2**level, 8)


def check_image_batch(x: torch.Tensor, channels: int, size: int | None, network: str) -> None:
    """Raise ValueError unless ``x`` is ``N x channels x size x size`` (any square size if ``size`` is None)."""
    shape = tuple(x.shape)
    ok = x.dim() == 4 and shape[1] == channels
    if size is not None:
        ok = ok and shape[2] == shape[3] == size
    if not ok:
        expected = f"N x {channels} x {size} x {size}" if size is not None else f"N x {channels} x H x W"
        raise ValueError(f"{network}: expected {expected} input, got shape {shape}")


def checked_latent(latent: int) -> int:
    """Return ``latent`` (a generator's code channels) if it is an integer >= 0; raise ValueError otherwise."""
    if isinstance(latent, bool) or not isinstance(latent, int) or latent < 0:
        raise ValueError(f"latent must be an integer >= 0, got {latent!r}")
    return latent


def check_batchnorm_values(batch: int, map_shapes: list[tuple[int, int]], network: str, remedy: str) -> None:
    """Raise ValueError when a training batch of ``batch`` images leaves a BatchNorm layer one value per
    channel (``batch * H * W == 1`` for one of ``map_shapes``, the ``(H, W)`` each BatchNorm normalises):
    batch statistics are undefined there (torch's own error names neither the setting nor the layer)."""
    for index, (height, width) in enumerate(map_shapes):
        if batch * height * width == 1:
            raise ValueError(
                f"{network}: BatchNorm layer {index + 1} of {len(map_shapes)} normalises a {height} x {width} map, "
                f"so a training batch of {batch} image leaves it one value per channel; {remedy}"
            )


class NoiseInjection(nn.Module):
    """x + s_c * n over an N x C x H x W map: one N(0, 1) noise map n per image, shared by the channels, scaled per
    channel by a learned strength s (StyleGAN's noise inputs and their per-channel factors B, Karras et al. 2019),
    which starts at 0 so the layer starts as the identity. Without ``seeds`` n comes from torch's global generator
    (training); given ``seeds`` (eval mode: :func:`content_seeds` of the generator's input) each image's map comes
    from its own seed mixed with the map's side, so an image gets the same detail in any batch, at any position,
    and two images share a map only if their seeds collide."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.strength = nn.Parameter(torch.zeros(channels))

    def forward(self, x: torch.Tensor, seeds: list[int] | None = None) -> torch.Tensor:
        shape = (x.shape[0], 1, x.shape[2], x.shape[3])
        if seeds is None:
            noise = torch.randn(shape, device=x.device, dtype=x.dtype)
        else:
            mixed = [(seed * 131 + x.shape[2]) % (2**31 - 1) for seed in seeds]  # another map at each side
            noise = seeded_maps(shape[1:], mixed).to(x.device, x.dtype)
        return x + self.strength.view(1, -1, 1, 1).to(x.dtype) * noise


def seeded_maps(shape: tuple[int, ...], seeds: list[int]) -> torch.Tensor:
    """One N(0, 1) tensor of ``shape`` per seed, each from its own generator (CPU, float32), stacked."""
    return torch.stack([torch.randn(shape, generator=torch.Generator().manual_seed(seed)) for seed in seeds])


def run_block(block: nn.Sequential, x: torch.Tensor, seeds: list[int] | None) -> torch.Tensor:
    """``block``'s layers in order on ``x``, each :class:`NoiseInjection` given ``seeds``."""
    for layer in block:
        x = layer(x, seeds) if isinstance(layer, NoiseInjection) else layer(x)
    return x


def content_seeds(x: torch.Tensor) -> list[int]:
    """One seed per image of ``x`` (N x C x H x W, model range: uint8 levels / 127.5 - 1): its levels
    round((x + 1) * 127.5) weighted by position (1 + index mod 65521), summed, mod 2**31 - 1. Equal images get equal
    seeds whatever batch they sit in; images that differ in one level get different ones."""
    levels = torch.round((x.detach().float() + 1) * 127.5).to(torch.int64).flatten(1).cpu()
    weights = torch.arange(levels.shape[1], dtype=torch.int64) % 65521 + 1
    return ((levels * weights).sum(1) % (2**31 - 1)).tolist()


class OutputGrain(nn.Module):
    """clamp(y + s * n, -1, 1) on a generator's output y in [-1, 1]: one N(0, 1) map n per image, added alike to every
    channel (grain in brightness, as a sensor's; strengths per channel on one map let V2T learn opposite signs, that is
    coloured grain on a grey sensor: benchmarks/README.md, Sixty-ninth round), scaled by one learned strength s that
    starts at 0 (StyleGAN's noise inputs, Karras et al. 2019, placed after the output's tanh so that bright, saturated
    fields get grain too). Training draws n from torch's global generator; given ``seeds`` (eval mode:
    :func:`content_seeds` of the generator's input) each image's map comes from its own seed, so an image gets the
    same grain in any batch and two images share a map only if their seeds collide (mod 2**31 - 1)."""

    def __init__(self) -> None:
        super().__init__()
        self.strength = nn.Parameter(torch.zeros(()))

    def forward(self, y: torch.Tensor, seeds: list[int] | None = None) -> torch.Tensor:
        shape = (y.shape[0], 1, y.shape[2], y.shape[3])
        if seeds is None:
            noise = torch.randn(shape, device=y.device, dtype=y.dtype)
        else:
            noise = seeded_maps(shape[1:], seeds).to(y.device, y.dtype)
        return (y + self.strength.to(y.dtype) * noise).clamp(-1.0, 1.0)


class UNetGenerator(nn.Module):
    """U-Net mapping an ``N x in_channels x size x size`` image to ``N x out_channels x size x size`` in [-1, 1].

    The encoder has ``depth = log2(size)`` stride-2 levels (bottleneck 1x1); the decoder mirrors it and
    concatenates each upsampled map with the encoder output of equal resolution. Dropout follows the
    ReLU of the ``min(3, depth - 2)`` decoder levels nearest the bottleneck (omitted if ``dropout == 0``).
    ``skips`` keeps only that many skip connections, the ones nearest the bottleneck (coarse layout), and
    drops the finer ones that copy the input's geometry into the output (None: all ``depth - 1``, the U-Net).
    ``latent`` k > 0 adds a random code z ~ N(0, I_k) per image, broadcast over the image as k more input
    channels (BicycleGAN's "add to input", Zhu et al. 2017), so one input can give several outputs;
    :meth:`forward` draws z from torch's global generator unless it is given (N x k). ``latent_map`` draws z per
    pixel instead (N x k x S x S: noise inputs, as StyleGAN's per-pixel noise, Karras et al. 2019), so the code
    can place texture where the input is uniform. ``in_channels``
    counts the image and conditioning channels only. ``upsample`` 'resize' doubles each decoder level by
    :func:`resize_conv` instead of a transposed convolution ('transpose', pix2pix's); 'bilinear' by
    :func:`bilinear_conv` (resize with a blur after it); 'subpixel' by
    :class:`SubpixelConv`, which starts as 'resize' does and may learn sub-pixel detail; 'balanced' by
    :class:`BalancedTransposedConv` (transposed, without the checkerboard or frame of a constant input). ``padding`` 'reflect' pads
    the encoder's convolutions by reflection where their input is larger than 2 px (the bottleneck's keeps zeros),
    so that no level sees a zero frame that tells it where the border is ('zeros', pix2pix's).
    ``grey_output`` draws one channel and repeats it ``out_channels`` times (:func:`grey_targets`: for targets
    that are grey, such as a monochrome optical-tactile sensor's, an output can then never carry a colour cast).
    ``inject`` n > 0 feeds the input's last n channels (the condition's class maps or reference, then z; see
    ``in_channels``) again into every encoder level, area-averaged to that level's side and concatenated to its
    input (BicycleGAN's "add to all", Zhu et al. 2017), so the class and the code cannot fade in the first levels.
    ``decoder_noise`` n > 0 adds a :class:`NoiseInjection` after the upsampling of each of the n finest decoder levels
    below the output (sides S/2, S/4, ...; all ``depth - 1`` of them where n is larger): per-pixel noise that can
    place fine detail, not layout (StyleGAN), seeded by the input in eval mode. ``output_grain`` adds an
    :class:`OutputGrain` after the output's tanh: per-pixel grain that varies per image, seeded by the input in eval
    mode.
    """

    def __init__(
        self,
        size: int,
        ngf: int = 64,
        kernel: int = 4,
        in_channels: int = 3,
        out_channels: int = 3,
        dropout: float = 0.5,
        skips: int | None = None,
        latent: int = 0,
        upsample: str = "transpose",
        padding: str = "zeros",
        latent_map: bool = False,
        grey_output: bool = False,
        inject: int = 0,
        decoder_noise: int = 0,
        output_grain: bool = False,
    ) -> None:
        super().__init__()
        if upsample not in UPSAMPLINGS:
            raise ValueError(f"upsample must be one of {UPSAMPLINGS}, got {upsample!r}")
        if padding not in PADDINGS:
            raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
        self.upsample, self.padding = upsample, padding
        up = {"transpose": lambda i, o, bias: upsampling_conv(i, o, kernel, bias), "resize": resize_conv,
              "bilinear": bilinear_conv, "subpixel": SubpixelConv,
              "balanced": lambda i, o, bias: balanced_upsampling_conv(i, o, kernel, bias)}[upsample]
        self.latent, self.latent_map = checked_latent(latent), bool(latent_map)
        check_kernel(kernel)
        if not 0.0 <= dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {dropout!r}")
        self.size = check_size(size)
        self.depth = unet_depth(size)
        if skips is not None and (isinstance(skips, bool) or not isinstance(skips, int) or skips < 0):
            raise ValueError(f"skips must be None or an integer >= 0, got {skips!r}")
        self.skips = self.depth - 1 if skips is None else min(skips, self.depth - 1)
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.grey_output = bool(grey_output)
        if isinstance(inject, bool) or not isinstance(inject, int) or not 0 <= inject <= in_channels + latent:
            raise ValueError(f"inject must be an integer in [0, {in_channels + latent}] (the input's channels), got {inject!r}")
        self.inject = inject
        if isinstance(decoder_noise, bool) or not isinstance(decoder_noise, int) or decoder_noise < 0:
            raise ValueError(f"decoder_noise must be an integer >= 0, got {decoder_noise!r}")
        self.decoder_noise = min(decoder_noise, self.depth - 1)  # at most every decoder level below the output
        self.ngf = ngf
        depth = self.depth
        widths = [encoder_width(level, ngf) for level in range(depth)]

        encoder: list[nn.Module] = []
        for level in range(depth):
            source = in_channels + latent if level == 0 else widths[level - 1] + inject
            mode = padding if size >> level > 2 else "zeros"  # the input side of this level
            conv = downsampling_conv(source, widths[level], kernel, level in (0, depth - 1), mode)
            if level == 0:
                block = nn.Sequential(conv, nn.LeakyReLU(0.2))
            elif level == depth - 1:
                block = nn.Sequential(conv, nn.ReLU())
            else:
                block = nn.Sequential(conv, nn.BatchNorm2d(widths[level]), nn.LeakyReLU(0.2))
            encoder.append(block)
        self.encoder = nn.ModuleList(encoder)

        # Decoder level j upsamples 2**j -> 2**(j+1); its output joins encoder level depth-2-j.
        self.dropout_levels = min(3, depth - 2) if dropout > 0 else 0
        decoder: list[nn.Module] = []
        for level in range(depth):
            source = widths[depth - 1] if level == 0 else (2 if level <= self.skips else 1) * widths[depth - 1 - level]
            if level == depth - 1:
                block = nn.Sequential(up(source, 1 if self.grey_output else out_channels, bias=True), nn.Tanh())
            else:
                target = widths[depth - 2 - level]
                layers: list[nn.Module] = [up(source, target, bias=False)]
                if level >= depth - 1 - self.decoder_noise:
                    layers.append(NoiseInjection(target))
                layers += [nn.BatchNorm2d(target), nn.ReLU()]
                if level < self.dropout_levels:
                    layers.append(nn.Dropout(dropout))
                block = nn.Sequential(*layers)
            decoder.append(block)
        self.decoder = nn.ModuleList(decoder)
        self.grain = OutputGrain() if output_grain else None
        self.apply(init_weights)

    def forward(self, x: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        x = with_latent_code(self, x, z)
        seeds = content_seeds(x) if (self.grain is not None or self.decoder_noise) and not self.training else None
        skips = []
        code = x[:, x.shape[1] - self.inject:] if self.inject else None
        for level, block in enumerate(self.encoder):
            x = block(x if code is None or level == 0 else with_injected(x, code))
            skips.append(x)
        x = run_block(self.decoder[0], skips[-1], seeds)
        for level in range(1, self.depth):
            joined = torch.cat([x, skips[self.depth - 1 - level]], dim=1) if level <= self.skips else x
            x = run_block(self.decoder[level], joined, seeds)
        if self.grain is not None:
            x = self.grain(x, seeds)
        return x.repeat(1, self.out_channels, 1, 1) if self.grey_output else x

    def encode(self, x: torch.Tensor, levels: tuple[int, ...]) -> list[torch.Tensor]:
        """The encoder's outputs at ``levels`` (0-based, ascending) for ``x`` (N x in_channels x S x S) with a zero
        latent code: the features PatchNCE compares (:mod:`vtgen.core.patchnce`). BatchNorm normalises by the
        batch's statistics as in training, but its running statistics are left as they were."""
        return encoder_outputs(self, self.encoder, x, levels, self.inject)

    @property
    def feature_levels(self) -> int:
        """Encoder levels :meth:`encode` may return (all but the 1x1 bottleneck)."""
        return self.depth - 1

    def feature_width(self, level: int) -> int:
        """Channels of :meth:`encode`'s output at ``level``."""
        return encoder_width(level, self.ngf)


def latent_shape(generator: nn.Module, n: int) -> tuple[int, ...]:
    """Shape of ``n`` latent codes of ``generator``: N x k, or N x k x S x S with ``latent_map`` (one code per pixel)."""
    if getattr(generator, "latent_map", False):
        return (n, generator.latent, generator.size, generator.size)
    return (n, generator.latent)


def with_latent_code(generator: nn.Module, x: torch.Tensor, z: torch.Tensor | None) -> torch.Tensor:
    """``x`` (checked: N x generator.in_channels x S x S) with the generator's latent code z (shape
    :func:`latent_shape`; drawn from torch's global generator when None) as k more channels, broadcast over the
    image unless it is a map; ``x`` itself when the generator has no code (``latent`` 0, where a given ``z`` is
    refused)."""
    name = type(generator).__name__
    check_image_batch(x, generator.in_channels, generator.size, name)
    if not generator.latent:
        if z is not None:
            raise ValueError(f"{name}: this generator has no latent code (latent 0)")
        return x
    shape = latent_shape(generator, x.shape[0])
    if z is None:
        z = torch.randn(shape, device=x.device)
    if tuple(z.shape) != shape:
        raise ValueError(f"{name}: expected a code of shape {shape}, got {tuple(z.shape)}")
    if z.dim() == 4:
        return torch.cat([x, z.to(x.dtype)], dim=1)
    return torch.cat([x, z.to(x.dtype)[:, :, None, None].expand(-1, -1, x.shape[2], x.shape[3])], dim=1)


def with_injected(x: torch.Tensor, code: torch.Tensor) -> torch.Tensor:
    """``x`` with ``code`` (N x n x S x S) area-averaged to x's side as n more channels (:class:`UNetGenerator`'s inject)."""
    return torch.cat([x, F.adaptive_avg_pool2d(code, x.shape[-2:]).to(x.dtype)], dim=1)


def encoder_outputs(generator: nn.Module, levels_in_order: nn.ModuleList, x: torch.Tensor,
                    levels: tuple[int, ...], inject: int = 0) -> list[torch.Tensor]:
    """The outputs of ``levels_in_order[l]`` for l in ``levels`` (0-based, ascending), run on ``x`` with a zero
    latent code: the features PatchNCE compares (:mod:`vtgen.core.patchnce`). BatchNorm normalises by the
    batch's statistics as in training, but its running statistics and counters are left as they were.
    ``inject``: the U-Net's (its input's last channels fed again to every level after the first)."""
    check_image_batch(x, generator.in_channels, generator.size, type(generator).__name__)
    if generator.latent:
        x = torch.cat([x, x.new_zeros(x.shape[0], generator.latent, x.shape[2], x.shape[3])], dim=1)
    norms = [m for m in levels_in_order.modules() if isinstance(m, nn.BatchNorm2d)]
    momenta, counts = [m.momentum for m in norms], [m.num_batches_tracked.clone() for m in norms]
    outputs = []
    code = x[:, x.shape[1] - inject:] if inject else None
    try:
        for m in norms:
            m.momentum = 0.0  # running = (1 - 0)·running + 0·batch: unchanged
        for level, block in enumerate(levels_in_order[:max(levels) + 1]):
            x = block(x if code is None or level == 0 else with_injected(x, code))
            if level in levels:
                outputs.append(x)
    finally:
        for m, momentum, count in zip(norms, momenta, counts):
            m.momentum = momentum
            m.num_batches_tracked.copy_(count)
    return outputs


RESNET_GROUPS = 8  # GroupNorm groups in the ResNet generator (fewer when a width is not a multiple of 8)


def group_norm(channels: int) -> nn.GroupNorm:
    """GroupNorm over ``channels`` in up to :data:`RESNET_GROUPS` groups (Wu & He 2018): per image, so a
    generator computes in evaluation exactly what it trained on. BatchNorm on the class-paired batch of 4 (two
    rows per class) learned running statistics its batches never had: the ResNet's eval-mode outputs went
    flat or black while its train-mode ones carried texture (benchmarks/README.md, "Eighth round"). Groups,
    unlike instance norm, keep a constant code or class channel's offsets relative to the other channels."""
    return nn.GroupNorm(math.gcd(RESNET_GROUPS, channels), channels)


class ResidualBlock(nn.Module):
    """x + F(x), F = [3x3 conv, GroupNorm, ReLU, 3x3 conv, GroupNorm], reflection-padded (He et al. 2016;
    Johnson et al. 2016's transformation block)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1, padding_mode="reflect", bias=False), group_norm(channels),
            nn.ReLU(),
            nn.Conv2d(channels, channels, 3, padding=1, padding_mode="reflect", bias=False), group_norm(channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


GENERATORS = ("unet", "resnet")
RESNET_BLOCKS = 6  # residual blocks at a quarter of the side (CycleGAN: 6 at 128 px)


class ResnetGenerator(nn.Module):
    """Fully convolutional translator for texture: ``N x in_channels x S x S`` to ``N x out_channels x S x S`` in
    [-1, 1] (Johnson et al. 2016; the generator of CycleGAN and CUT, which translate without aligned pairs).

    A 7x7 conv at full side (level 0, ngf channels), two stride-2 3x3 convs (levels 1 and 2: 2·ngf at S/2,
    4·ngf at S/4), ``blocks`` :class:`ResidualBlock` at S/4, two nearest 2x + 3x3 conv upsamplings (no
    checkerboard, Odena et al. 2016) and a 7x7 conv with tanh; :func:`group_norm` and ReLU between, every
    convolution reflection-padded. No path reaches a 1x1 bottleneck, so no level draws one image-wide layout (the
    U-Net's dark-framed blobs on class pairs) and the borders are not zero-padded. ``latent`` and ``latent_map``
    are the U-Net's (:func:`with_latent_code`), and so is ``grey_output``.
    """

    def __init__(self, size: int, ngf: int = 32, in_channels: int = 3, out_channels: int = 3, latent: int = 0,
                 blocks: int = RESNET_BLOCKS, latent_map: bool = False, grey_output: bool = False) -> None:
        super().__init__()
        self.size, self.ngf, self.latent = check_size(size), ngf, checked_latent(latent)
        self.latent_map, self.grey_output = bool(latent_map), bool(grey_output)
        self.in_channels, self.out_channels = in_channels, out_channels

        def conv(i: int, o: int, kernel: int, stride: int = 1, bias: bool = False) -> nn.Conv2d:
            return nn.Conv2d(i, o, kernel, stride=stride, padding=kernel // 2, padding_mode="reflect", bias=bias)

        def normed(*layers: nn.Module, width: int) -> nn.Sequential:
            return nn.Sequential(*layers, group_norm(width), nn.ReLU())

        widths = [self.feature_width(level) for level in range(3)]
        self.encoder = nn.ModuleList([
            normed(conv(in_channels + latent, widths[0], 7), width=widths[0]),
            normed(conv(widths[0], widths[1], 3, stride=2), width=widths[1]),
            normed(conv(widths[1], widths[2], 3, stride=2), width=widths[2]),
        ])
        self.blocks = nn.Sequential(*(ResidualBlock(widths[2]) for _ in range(blocks)))
        self.decoder = nn.Sequential(
            normed(nn.Upsample(scale_factor=2, mode="nearest"), conv(widths[2], widths[1], 3), width=widths[1]),
            normed(nn.Upsample(scale_factor=2, mode="nearest"), conv(widths[1], widths[0], 3), width=widths[0]),
            conv(widths[0], 1 if self.grey_output else out_channels, 7, bias=True), nn.Tanh())
        self.apply(init_weights)

    feature_levels = 3  # levels :meth:`encode` may return: the 7x7 stem and the two stride-2 convs

    def feature_width(self, level: int) -> int:
        """Channels at encoder ``level`` (0, 1, 2): ngf, 2·ngf, 4·ngf."""
        return self.ngf * 2 ** level

    def forward(self, x: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        x = with_latent_code(self, x, z)
        for block in self.encoder:
            x = block(x)
        x = self.decoder(self.blocks(x))
        return x.repeat(1, self.out_channels, 1, 1) if self.grey_output else x

    def encode(self, x: torch.Tensor, levels: tuple[int, ...]) -> list[torch.Tensor]:
        """The encoder's outputs at ``levels`` (:func:`encoder_outputs`)."""
        return encoder_outputs(self, self.encoder, x, levels)


def grey_targets(images: torch.Tensor) -> bool:
    """True when every image of uint8 N x 3 x S x S ``images`` (N > 0) is grey: R = G = B at every pixel, as a
    monochrome sensor's frames are once decoded to three channels."""
    return len(images) > 0 and images.shape[1] == 3 and bool(
        torch.equal(images[:, 0], images[:, 1]) and torch.equal(images[:, 1], images[:, 2]))


def build_generator(settings: dict, in_channels: int = 3) -> nn.Module:
    """The generator ``settings`` name (``generator``: 'unet', the default, or 'resnet'), from its size, ngf,
    latent, latent_map and (the U-Net's) kernel, skips, upsample, padding, inject_every_level, decoder_noise and output_grain
    keys. The ResNet always resizes and reflects, so it ignores ``upsample`` and ``padding``; it has no skip connections, so
    ``skips`` other than all (None) is refused, and so are ``inject_every_level``, ``decoder_noise`` and ``output_grain``. Raises ValueError for
    that and for an unknown kind. ``grey_output`` (absent: False) makes either draw one channel, repeated."""
    kind = settings.get("generator", "unet")
    latent, latent_map = settings.get("latent", 0), settings.get("latent_map", False)
    grey = settings.get("grey_output", False)
    if kind == "unet":
        # inject_every_level: the condition's channels (all but the 3 image channels) and z, again at every level
        inject = in_channels - 3 + latent if settings.get("inject_every_level") else 0
        return UNetGenerator(settings["size"], settings["ngf"], settings["kernel"], in_channels=in_channels,
                             skips=settings.get("skips"), latent=latent,
                             upsample=settings.get("upsample", "transpose"), padding=settings.get("padding", "zeros"),
                             latent_map=latent_map, grey_output=grey, inject=inject,
                             decoder_noise=settings.get("decoder_noise", 0),
                             output_grain=bool(settings.get("output_grain", False)))
    if settings.get("output_grain"):
        raise ValueError(f"class_gan.output_grain is a U-Net setting: set it to false with class_gan.generator: {kind}")
    if settings.get("inject_every_level"):
        raise ValueError("class_gan.inject_every_level is a U-Net setting: set it to false with class_gan.generator: "
                         f"{kind}")
    if settings.get("decoder_noise"):
        raise ValueError(f"class_gan.decoder_noise is a U-Net setting: set it to 0 with class_gan.generator: {kind}")
    if kind == "resnet":
        if settings.get("skips") is not None:
            raise ValueError(f"class_gan.skips ({settings['skips']}) is a U-Net setting: set it to 'all' with "
                             f"class_gan.generator: resnet, which has no skip connections")
        return ResnetGenerator(settings["size"], settings["ngf"], in_channels=in_channels, latent=latent,
                               latent_map=latent_map, grey_output=grey)
    raise ValueError(f"unknown generator {kind!r} (allowed: {', '.join(GENERATORS)})")


def fixed_codes(generator: nn.Module, n: int, seed: int = 0) -> torch.Tensor | None:
    """``n`` latent codes for ``generator`` (:func:`latent_shape`, z ~ N(0, I)) from a generator seeded with ``seed``, so
    that translating and validating neither draw from nor depend on torch's global generator; None without
    a latent code."""
    latent = getattr(generator, "latent", 0)
    return torch.randn(latent_shape(generator, n), generator=torch.Generator().manual_seed(seed)) if latent else None


class GlobalDiscriminator(nn.Module):
    """Image-level discriminator: four stride-2 convs (widths ndf, 2ndf, 4ndf, 8ndf), flatten, one linear
    layer. Input ``N x in_channels x size x size``; output ``N x 1`` raw logits."""

    def __init__(self, size: int, ndf: int = 64, kernel: int = 5, in_channels: int = 6) -> None:
        super().__init__()
        check_kernel(kernel)
        self.size = check_size(size)
        self.in_channels = in_channels
        widths = [ndf, 2 * ndf, 4 * ndf, 8 * ndf]
        layers: list[nn.Module] = [downsampling_conv(in_channels, widths[0], kernel, bias=True), nn.LeakyReLU(0.2)]
        for source, target in zip(widths[:-1], widths[1:]):
            layers += [downsampling_conv(source, target, kernel, bias=False), nn.BatchNorm2d(target), nn.LeakyReLU(0.2)]
        self.features = nn.Sequential(*layers)
        final_side = size // 16
        self.classifier = nn.Linear(widths[-1] * final_side * final_side, 1)
        self.apply(init_weights)

    def batchnorm_sides(self) -> list[int]:
        """Side of the map each BatchNorm normalises: ``size / 4``, ``size / 8``, ``size / 16``."""
        return [self.size // 4, self.size // 8, self.size // 16]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_image_batch(x, self.in_channels, self.size, type(self).__name__)
        if self.training:
            check_batchnorm_values(x.shape[0], [(s, s) for s in self.batchnorm_sides()], type(self).__name__,
                                   f"use batch_size >= 2 or size >= 32 (size is {self.size})")
        return self.classifier(torch.flatten(self.features(x), 1))


def stride1_padding(kernel: int) -> int:
    """Padding of the PatchGAN stride-1 convs: 1 for k=4 (side shrinks by 1, as in pix2pix), 2 for k=5 (kept)."""
    check_kernel(kernel)
    return 1 if kernel == 4 else 2


class PatchDiscriminator(nn.Module):
    """PatchGAN discriminator: ``layers`` stride-2 convs, then two stride-1 convs, giving an
    ``N x 1 x H' x W'`` map of raw logits (64 px, layers=3, kernel=4 -> 6 x 6). Any input side large
    enough for the depth is accepted (see :meth:`output_side`)."""

    def __init__(self, ndf: int = 64, layers: int = 3, kernel: int = 4, in_channels: int = 6) -> None:
        super().__init__()
        check_kernel(kernel)
        if isinstance(layers, bool) or not isinstance(layers, int) or layers < 1:
            raise ValueError(f"layers must be an integer >= 1, got {layers!r}")
        self.layers = layers
        self.kernel = kernel
        self.in_channels = in_channels
        padding = stride1_padding(kernel)
        blocks: list[nn.Module] = [downsampling_conv(in_channels, ndf, kernel, bias=True), nn.LeakyReLU(0.2)]
        width = ndf
        for n in range(1, layers):
            target = encoder_width(n, ndf)
            blocks += [downsampling_conv(width, target, kernel, bias=False), nn.BatchNorm2d(target), nn.LeakyReLU(0.2)]
            width = target
        target = encoder_width(layers, ndf)
        blocks += [
            nn.Conv2d(width, target, kernel, stride=1, padding=padding, bias=False),
            nn.BatchNorm2d(target),
            nn.LeakyReLU(0.2),
            nn.Conv2d(target, 1, kernel, stride=1, padding=padding, bias=True),
        ]
        self.model = nn.Sequential(*blocks)
        self.apply(init_weights)

    def output_side(self, side: int) -> int:
        """Side of the logit map for an input side ``side`` (<= 0 means the input is too small);
        every intermediate map must be at least 1 pixel, otherwise 0 is returned."""
        down_padding, _ = resampling_padding(self.kernel)
        for _ in range(self.layers):
            side = (side + 2 * down_padding - self.kernel) // 2 + 1
            if side < 1:
                return 0
        same_padding = stride1_padding(self.kernel)
        for _ in range(2):
            side = side + 2 * same_padding - self.kernel + 1
            if side < 1:
                return 0
        return side

    def batchnorm_sides(self, side: int) -> list[int]:
        """Side of the map each BatchNorm normalises for an input side ``side`` (strided layers 2..layers,
        then the first stride-1 conv); only meaningful when :meth:`output_side` is >= 1."""
        down_padding, _ = resampling_padding(self.kernel)
        sides = []
        for n in range(self.layers):
            side = (side + 2 * down_padding - self.kernel) // 2 + 1
            if n > 0:
                sides.append(side)
        sides.append(side + 2 * stride1_padding(self.kernel) - self.kernel + 1)
        return sides

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_image_batch(x, self.in_channels, None, type(self).__name__)
        height, width = x.shape[-2:]
        if self.output_side(height) < 1 or self.output_side(width) < 1:
            raise ValueError(
                f"PatchDiscriminator: input of size {height} x {width} is too small for layers={self.layers} "
                f"with kernel {self.kernel}"
            )
        if self.training:
            check_batchnorm_values(x.shape[0], list(zip(self.batchnorm_sides(height), self.batchnorm_sides(width))),
                                   type(self).__name__,
                                   f"use batch_size >= 2, fewer patch_layers (now {self.layers}) or a larger size "
                                   f"(input {height} x {width}, kernel {self.kernel})")
        return self.model(x)


class BinomialBlur(nn.Module):
    """Fixed depthwise [1, 2, 1]/4 x [1, 2, 1]/4 low-pass, reflection-padded, side kept: zero response at period 2,
    half at period 4. Before a stride-2 conv it keeps the conv from aliasing fine patterns, and, as its own adjoint,
    keeps the conv's gradient (a transposed conv's lattice) out of what the input is taught (anti-aliased
    downsampling: Zhang 2019; StyleGAN2's discriminator, Karras et al. 2020). No parameters."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        taps = torch.tensor([1.0, 2.0, 1.0])
        kernel = (taps[:, None] * taps[None, :]) / 16.0
        self.register_buffer("kernel", kernel.expand(channels, 1, 3, 3).clone(), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), self.kernel.to(x.dtype), groups=x.shape[1])


class ProjectionDiscriminator(nn.Module):
    """Class-aware PatchGAN for class-paired data: judges an image (not a condition-image pair) *as an image
    of class c*. A PatchGAN trunk without BatchNorm (``layers`` stride-2 convs and one stride-1 conv,
    LeakyReLU 0.2) gives features φ (N x K x H' x W'); each patch's logit is ψ(φ) + ⟨e_c, φ⟩, a 1x1 conv plus
    the inner product with a learned embedding of the class (the projection discriminator of Miyato &
    Koyama 2018, eq. 3, per patch), every layer spectrally normalised. No BatchNorm, so the R1 penalty's
    input gradient is per image.
    With ``antialias`` the trunk starts with a 3x3 stride-1 conv at full side (ndf/2 maps, LeakyReLU), which can
    see a period-2 pattern, and a :class:`BinomialBlur` precedes each stride-2 conv (StyleGAN2's discriminator,
    Karras et al. 2020): D's input gradient, which teaches the generator, then carries no lattice of the strided
    convs, and D is not blind to the finest one (a blur alone made it so: benchmarks/README.md, Fifty-ninth round).
    Input ``N x in_channels x S x S`` and ``N`` class indices; output ``N x 1 x H' x W'`` raw logits."""

    def __init__(self, num_classes: int, ndf: int = 64, layers: int = 3, kernel: int = 4,
                 in_channels: int = 3, class_head: bool = False, antialias: bool = False) -> None:
        super().__init__()
        check_kernel(kernel)
        if isinstance(layers, bool) or not isinstance(layers, int) or layers < 1:
            raise ValueError(f"layers must be an integer >= 1, got {layers!r}")
        if num_classes < 1:
            raise ValueError(f"a projection discriminator needs at least one class, got {num_classes}")
        self.in_channels, self.num_classes = in_channels, num_classes
        blocks: list[nn.Module] = []
        width = in_channels
        if antialias:
            blocks += [nn.Conv2d(width, max(ndf // 2, 1), 3, padding=1, padding_mode="reflect"), nn.LeakyReLU(0.2)]
            width = max(ndf // 2, 1)
        for n in range(layers):
            target = encoder_width(n, ndf)
            blocks += [BinomialBlur(width)] if antialias else []
            blocks += [downsampling_conv(width, target, kernel, bias=True), nn.LeakyReLU(0.2)]
            width = target
        target = encoder_width(layers, ndf)
        blocks += [nn.Conv2d(width, target, kernel, stride=1, padding=stride1_padding(kernel), bias=True),
                   nn.LeakyReLU(0.2)]
        self.trunk = nn.Sequential(*blocks)
        self.logit = nn.Conv2d(target, 1, 1)
        self.embedding = nn.Embedding(num_classes, target)
        self.apply(init_weights)
        nn.init.normal_(self.embedding.weight, 0.0, 0.02)
        # built last, so that without it the weights (and every draw) are those of the plain discriminator
        self.class_head = nn.Linear(target, num_classes) if class_head else None
        # Spectral normalisation (Miyato et al. 2018), as in the projection discriminator's paper: each layer's
        # largest singular value is 1. Without it (and without BatchNorm) the N(0, 0.02) weights shrink the
        # signal about 3x per layer: logits of std 0.0015 at the start, and D stayed at chance (loss 0.69).
        for module in self.modules():
            if isinstance(module, (nn.Conv2d, nn.Linear, nn.Embedding)):
                spectral_norm(module)

    def forward(self, x: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        return self.judge(x, labels)[0]

    def judge(self, x: torch.Tensor, labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The patch logits of :meth:`forward` and :meth:`class_logits`, from one pass of the trunk."""
        features = self.features(x)
        return self.patch_logits(features, labels), self.class_logits(features)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """The trunk's features φ(x) (N x K x H' x W'), for :meth:`patch_logits` under several labellings."""
        check_image_batch(x, self.in_channels, None, type(self).__name__)
        return self.trunk(x)

    def patch_logits(self, features: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """ψ(φ) + ⟨e_c, φ⟩ per patch for trunk ``features`` and ``labels`` (N class indices)."""
        if labels.shape != (features.shape[0],):
            raise ValueError(f"{type(self).__name__}: expected {features.shape[0]} class indices, got shape "
                             f"{tuple(labels.shape)}")
        projection = (self.embedding(labels.to(features.device))[:, :, None, None] * features).sum(dim=1, keepdim=True)
        return self.logit(features) + projection

    def class_logits(self, features: torch.Tensor) -> torch.Tensor | None:
        """With ``class_head``, class logits (N x num_classes) of a linear layer on trunk ``features`` averaged over
        the patches (the auxiliary classifier of AC-GAN, Odena et al. 2017); None without it."""
        return None if self.class_head is None else self.class_head(features.mean(dim=(2, 3)))


def build_discriminator(kind: str, size: int, ndf: int, kernel: int, patch_layers: int,
                        in_channels: int = 6) -> nn.Module:
    """Discriminator of ``kind`` ("global" or "patch") for ``size`` px images with ``in_channels`` input
    channels (condition plus image). For "patch", ``size`` is checked to give a logit map of at least 1 x 1."""
    if kind == "global":
        return GlobalDiscriminator(size, ndf=ndf, kernel=kernel, in_channels=in_channels)
    if kind == "patch":
        check_size(size)
        net = PatchDiscriminator(ndf=ndf, layers=patch_layers, kernel=kernel, in_channels=in_channels)
        if net.output_side(size) < 1:
            raise ValueError(
                f"patch discriminator: size {size} is too small for patch_layers={patch_layers} with kernel {kernel}"
            )
        return net
    raise ValueError(f"unknown discriminator kind {kind!r}; allowed kinds: {', '.join(DISCRIMINATOR_KINDS)}")


def count_parameters(module: nn.Module) -> int:
    """Number of trainable (``requires_grad``) parameters of ``module``."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def conditional_pair(condition: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """What the discriminators see: ``condition`` and ``image`` concatenated along channels."""
    return torch.cat([condition, image], dim=1)
