"""Translating images with a trained generator: what the generate stage, the studies and the snapshot referee
(:mod:`vtgen.core.referee`) all call."""

from __future__ import annotations

import torch

from vtgen.core.conditioning import Conditioning
from vtgen.core.gan import to_model_range, to_uint8
from vtgen.core.models import fixed_codes


@torch.no_grad()
def translate(generator: torch.nn.Module, images: torch.Tensor, batch_size: int = 32,
              conditioning: Conditioning | None = None, labels: torch.Tensor | None = None,
              seed: int = 0, truncation: float = 1.0) -> torch.Tensor:
    """uint8 N x 3 x S x S -> uint8 N x 3 x S x S through ``generator`` (eval mode, no dropout); with a
    ``conditioning`` other than none, ``labels`` (N class indices) says what each image is asked to be.
    A generator with a latent code gets z ~ N(0, I) drawn from a generator seeded with ``seed`` (so the
    same call gives the same images; another seed, another draw), scaled by ``truncation`` psi: z' = psi z, the
    truncation trick in a space whose mean code is 0 (Karras et al. 2019; Brock et al. 2019 truncate z itself):
    psi < 1 trades diversity for typical outputs, 0 gives every input the mean code, 1 is the plain draw."""
    device = next(generator.parameters()).device
    conditioning = conditioning or Conditioning()
    if conditioning.needs_labels and (labels is None or len(labels) != len(images)):
        raise ValueError(f"a model conditioned on '{conditioning.kind}' needs one class per image")
    if not 0.0 <= truncation <= 1.0:
        raise ValueError(f"truncation must lie in [0, 1], got {truncation}")
    codes = fixed_codes(generator, len(images), seed)
    if codes is not None:
        codes = codes * truncation  # exact at psi 1: the plain draw
    out = []
    for i in range(0, len(images), batch_size):
        x = to_model_range(images[i:i + batch_size]).to(device)
        if conditioning.kind != "none":
            x = conditioning.condition(x, labels[i:i + batch_size] if conditioning.needs_labels else None)
        z = None if codes is None else codes[i:i + batch_size].to(device)
        out.append(to_uint8(generator(x, z)).cpu())
    return torch.cat(out) if out else images.clone()
