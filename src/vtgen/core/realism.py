"""Is one generated image like some real image? The realism score, and redrawing the latent code where it is not.

Kynkäänniemi et al. (2019, "Improved precision and recall metric for assessing generative models", section 5)
score one sample x against real samples y_i whose ball radius r_i is the distance to their k-th nearest real
neighbour: R(x) = max_i r_i / ||phi(x) - phi(y_i)||, over the balls with a radius at most the median (the
widest half, in sparse regions, are dropped, so an outlier's ball cannot vouch for anything). R >= 1 means x
lies inside some real ball: it is precise, in the sense of the precision metric.

phi here is each image's layout and colour: the mean of every channel over an ``side`` x ``side`` grid (area
resize), on [0, 1]. It sees a dark ground where every real touch is light, a wash of one colour or a blotch
where real images have none; it does not see fine texture, and it never sees the class.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

LAYOUT_SIDE = 8  # phi's grid: 8 x 8 means per channel
NEIGHBOURS = 3  # k of the real balls (the paper's)
ROW_BLOCK = 1024  # rows of a distance block, so that 7,000 real images never need 7,000 x 7,000 floats at once


def layout_features(images: torch.Tensor, side: int = LAYOUT_SIDE) -> torch.Tensor:
    """uint8 ``N x C x H x W`` -> float32 ``N x (C * side * side)``: each channel's area means on a side x side grid, / 255."""
    if images.ndim != 4 or images.dtype != torch.uint8:
        raise ValueError(f"layout_features needs uint8 N x C x H x W images, got {images.dtype} {tuple(images.shape)}")
    return F.adaptive_avg_pool2d(images.float(), side).flatten(1) / 255.0


class RealBalls:
    """The real images' balls (centre phi(y_i), radius r_i: distance to the k-th nearest other real image),
    keeping those with r_i at most the median; :meth:`score` gives R(x) for generated images."""

    def __init__(self, real_images: torch.Tensor, k: int = NEIGHBOURS, side: int = LAYOUT_SIDE):
        if len(real_images) <= k:
            raise ValueError(f"the realism score needs more than k = {k} real images, got {len(real_images)}")
        self.side = side
        feats = layout_features(real_images, side)
        radii = torch.cat([torch.cdist(feats[i:i + ROW_BLOCK], feats).kthvalue(k + 1, dim=1).values  # +1: itself at 0
                           for i in range(0, len(feats), ROW_BLOCK)])
        keep = radii <= radii.median()
        self.centres, self.radii = feats[keep], radii[keep]

    def score(self, images: torch.Tensor) -> torch.Tensor:
        """R(x) per image (float32 N): at least 1 inside some kept real ball (very large on a centre itself)."""
        feats = layout_features(images, self.side)
        out = []
        for i in range(0, len(feats), ROW_BLOCK):
            distance = torch.cdist(feats[i:i + ROW_BLOCK], self.centres).clamp_min(1e-12)
            out.append((self.radii[None, :] / distance).max(dim=1).values)
        return torch.cat(out) if out else torch.empty(0)
