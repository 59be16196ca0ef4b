"""Pure pieces of conditional-GAN training: image scaling, the paper's "noise", losses, optimisers.

Nothing here touches the file system, so each piece is unit-testable in milliseconds.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

GAN_LOSSES = ("bce", "lsgan")
OPTIMIZERS = ("adam", "rmsprop")
PAPER_NOISE_MARGIN = 30  # pixels added before the random crop, at the paper's 256 px


def to_model_range(images: torch.Tensor) -> torch.Tensor:
    """uint8 images in [0, 255] -> float32 in [-1, 1] (the generator's tanh range)."""
    return images.float() / 127.5 - 1.0


def to_uint8(images: torch.Tensor) -> torch.Tensor:
    """Float images in [-1, 1] -> uint8 in [0, 255], rounded; values outside are clipped."""
    return ((images.float().clamp(-1, 1) + 1.0) * 127.5).round().to(torch.uint8)


def noise_margin(size: int) -> int:
    """Pixels of the random-positioning margin: the paper's 30 px at 256, scaled with the size."""
    return max(2, round(PAPER_NOISE_MARGIN * size / 256))


def random_positioning(inputs: torch.Tensor, targets: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """The paper's "noise z": resize to size + margin, crop back to size at a random place, random flip.

    ``inputs`` and ``targets`` are N x C x S x S float batches; each pair gets the same crop and
    flip, so an aligned pair stays aligned. Random draws come from ``generator`` only.
    """
    n, _, size, _ = inputs.shape
    big = size + noise_margin(size)
    both = F.interpolate(torch.cat([inputs, targets], dim=1), size=(big, big), mode="bilinear", align_corners=False)
    offsets = torch.randint(0, big - size + 1, (n, 2), generator=generator)
    flips = torch.rand(n, generator=generator) < 0.5
    crops = []
    for i in range(n):
        y, x = int(offsets[i, 0]), int(offsets[i, 1])
        crop = both[i, :, y:y + size, x:x + size]
        crops.append(crop.flip(-1) if flips[i] else crop)
    out = torch.stack(crops)
    channels = inputs.shape[1]
    return out[:, :channels].contiguous(), out[:, channels:].contiguous()


def adversarial_loss(logits: torch.Tensor, real: bool, kind: str = "bce") -> torch.Tensor:
    """GAN loss on raw logits, averaged over the batch (and patches).

    ``bce``: sigmoid cross-entropy, computed stably from logits as
    max(l, 0) - l*t + log(1 + exp(-|l|)) (``binary_cross_entropy_with_logits``).
    ``lsgan``: least squares, mean((l - t)^2), with t = 1 for real and 0 for fake.
    """
    logits = logits.float()
    target = torch.full_like(logits, 1.0 if real else 0.0)
    if kind == "bce":
        return F.binary_cross_entropy_with_logits(logits, target)
    if kind == "lsgan":
        return F.mse_loss(logits, target)
    raise ValueError(f"unknown gan_loss '{kind}' (allowed: {', '.join(GAN_LOSSES)})")


def make_optimizer(params, name: str, lr: float, betas: tuple[float, float],
                   multi_tensor_on: str | None = None) -> torch.optim.Optimizer:
    """Adam with ``betas``, or RMSProp with decay 0.9 (TensorFlow's default, which the authors' code used).

    With ``multi_tensor_on`` (a torch device type) the step runs as one kernel over all parameters:
    fused Adam (on 'cpu' and 'cuda' only; elsewhere the default step) or foreach RMSprop; equal to the
    default step up to floating-point rounding.
    """
    if name == "adam":
        fused = multi_tensor_on in ("cpu", "cuda") or None
        return torch.optim.Adam(params, lr=lr, betas=tuple(betas), fused=fused)
    if name == "rmsprop":
        return torch.optim.RMSprop(params, lr=lr, alpha=0.9, eps=1e-10, foreach=bool(multi_tensor_on) or None)
    raise ValueError(f"unknown optimizer '{name}' (allowed: {', '.join(OPTIMIZERS)})")
