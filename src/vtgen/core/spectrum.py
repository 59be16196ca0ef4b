"""The log radial power profile of images: the score stage's spectrum metric
(:func:`vtgen.core.distribution.spectrum_distance`) and the training's optional spectral loss
(``spectrum_matching``) use this one formula, kept apart so that training does not depend on the
evaluation code."""

from __future__ import annotations

import math

import torch

QUANTISATION_PSD = (1 / 255) ** 2 / 12  # power spectral density of uint8 rounding noise, grey in [0, 1]
LUMA = (0.299, 0.587, 0.114)  # ITU-R BT.601


def log_radial_profiles(grey: torch.Tensor) -> torch.Tensor:
    """Per-image log10 radial power profiles of greyscale images in [0, 1], N x H x W -> N x (min(H, W) // 2),
    in the dtype and on the device of ``grey``, differentiable (the spectral loss of training uses it).

    The formula of :func:`vtgen.core.distribution.radial_power_spectrum`: a periodic Hann window w, the window-weighted mean
    removed, P = |FFT2(w * (grey - mean))|^2 / sum(w^2), bin k = round(S * |f|) for k = 1 .. S // 2,
    log10(mean P in bin + QUANTISATION_PSD)."""
    n, h, w = grey.shape
    side = min(h, w)
    hann = [0.5 - 0.5 * torch.cos(2 * math.pi * torch.arange(m, dtype=grey.dtype, device=grey.device) / m)
            for m in (h, w)]
    window = torch.outer(*hann)
    mean = (grey * window).sum(dim=(1, 2), keepdim=True) / window.sum()
    power = torch.fft.fft2((grey - mean) * window).abs().square() / window.square().sum()
    radius = torch.hypot(torch.fft.fftfreq(h, dtype=torch.float64)[:, None],
                         torch.fft.fftfreq(w, dtype=torch.float64)[None, :]) * side
    bins = torch.round(radius).long().flatten()
    keep = torch.nonzero((bins >= 1) & (bins <= side // 2)).flatten().to(grey.device)
    bins = bins.to(grey.device)[keep] - 1
    counts = torch.bincount(bins, minlength=side // 2).to(grey.dtype)
    sums = torch.zeros(n, side // 2, dtype=grey.dtype, device=grey.device).index_add_(
        1, bins, power.flatten(1)[:, keep])
    return torch.log10(sums / counts + QUANTISATION_PSD)


def rgb_log_radial_profiles(images: torch.Tensor) -> torch.Tensor:
    """:func:`log_radial_profiles` of N x 3 x S x S images in [-1, 1] (the generator's range), taken on
    their BT.601 grey in [0, 1]."""
    luma = torch.tensor(LUMA, dtype=images.dtype, device=images.device)
    return log_radial_profiles(torch.einsum("nchw,c->nhw", (images + 1) / 2, luma))
