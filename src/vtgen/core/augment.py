"""Differentiable augmentation of the images a discriminator sees (DiffAugment, Zhao et al. 2020).

With a few hundred training images a discriminator memorises them and its gradient stops teaching the
generator. Applying the same random, differentiable transformations to real *and* generated images before
the discriminator (never to what the generator is trained to produce) keeps it from memorising while the
generator still learns the un-augmented distribution (Zhao et al. 2020, eq. 4-5). Pure torch; every draw
comes from torch's global generator, which the train stage seeds and checkpoints.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SHIFT_FRACTION = 1 / 8   # translation: up to this share of the side, zero padding (Zhao et al.: 1/8)
CUTOUT_FRACTION = 1 / 2  # cutout: one square of this share of the side set to 0 (Zhao et al.: 1/2)


def colour(x: torch.Tensor) -> torch.Tensor:
    """Random brightness (+U(-0.5, 0.5)), saturation (x U(0, 2) about the grey) and contrast (x U(0.5, 1.5)
    about the mean), one draw per image, on ``[-1, 1]`` images (N x C x H x W)."""
    n = x.shape[0]
    x = x + (torch.rand(n, 1, 1, 1, device=x.device, dtype=x.dtype) - 0.5)
    grey = x.mean(dim=1, keepdim=True)
    x = (x - grey) * (torch.rand(n, 1, 1, 1, device=x.device, dtype=x.dtype) * 2) + grey
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    return (x - mean) * (torch.rand(n, 1, 1, 1, device=x.device, dtype=x.dtype) + 0.5) + mean


def translation(x: torch.Tensor, fraction: float = SHIFT_FRACTION) -> torch.Tensor:
    """Shift each image by a random whole number of pixels in [-fraction·side, fraction·side] on each axis,
    filling with zeros (a gather, so gradients reach every kept pixel)."""
    n, _, h, w = x.shape
    sy, sx = int(h * fraction + 0.5), int(w * fraction + 0.5)
    dy = torch.randint(-sy, sy + 1, (n, 1, 1), device=x.device)
    dx = torch.randint(-sx, sx + 1, (n, 1, 1), device=x.device)
    rows = torch.arange(h, device=x.device)[None, :, None] + dy  # N x H x 1: source row of each output row
    cols = torch.arange(w, device=x.device)[None, None, :] + dx  # N x 1 x W
    padded = F.pad(x, [1, 1, 1, 1])  # index 0 and side+1 are the zero border
    rows, cols = rows.clamp(-1, h) + 1, cols.clamp(-1, w) + 1
    batch = torch.arange(n, device=x.device)[:, None, None]
    return padded.permute(0, 2, 3, 1)[batch, rows, cols].permute(0, 3, 1, 2)


def cutout(x: torch.Tensor, fraction: float = CUTOUT_FRACTION) -> torch.Tensor:
    """Set one square of side fraction·side, at a random centre per image, to 0 (mid-grey on [-1, 1])."""
    n, _, h, w = x.shape
    ch, cw = int(h * fraction + 0.5), int(w * fraction + 0.5)
    top = torch.randint(0, h + 1, (n, 1, 1), device=x.device) - ch // 2  # centre anywhere on [0, side]
    left = torch.randint(0, w + 1, (n, 1, 1), device=x.device) - cw // 2
    rows = torch.arange(h, device=x.device)[None, :, None] - top
    cols = torch.arange(w, device=x.device)[None, None, :] - left
    inside = (rows >= 0) & (rows < ch) & (cols >= 0) & (cols < cw)  # N x H x W
    return x * (~inside)[:, None].to(x.dtype)


TRANSFORMS = {"colour": colour, "translation": translation, "cutout": cutout}  # in the order they apply
POLICY = tuple(TRANSFORMS)  # every transform: Zhao et al. 2020's "color,translation,cutout" policy


def augment_policy(setting: bool | list[str]) -> tuple[str, ...]:
    """The transforms a ``class_gan.diffaugment`` setting names, in :data:`POLICY` order: ``true`` = all three,
    ``false`` = none, or a list of their names. Raises ValueError naming an unknown transform."""
    if isinstance(setting, bool):
        return POLICY if setting else ()
    unknown = sorted(set(setting) - set(POLICY))
    if unknown:
        raise ValueError(f"class_gan.diffaugment: unknown transform {unknown} (allowed: {', '.join(POLICY)})")
    return tuple(name for name in POLICY if name in setting)


def diff_augment(x: torch.Tensor, policy: tuple[str, ...] = POLICY) -> torch.Tensor:
    """The transforms of ``policy`` in :data:`POLICY` order (the default: colour, then translation, then cutout,
    the "color,translation,cutout" policy of Zhao et al. 2020), each drawn independently per image. Shape and
    dtype are kept; gradients flow to ``x``."""
    for name, transform in TRANSFORMS.items():
        if name in policy:
            x = transform(x)
    return x
