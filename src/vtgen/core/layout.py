"""Is a photo a texture or a scene? The layout gap of an image, for ``translation.recipe: auto``.

A macro photo of a fabric is a texture: any part of it looks like any other, so the means of its
blocks hardly differ. A photo of an object is a scene: object and background, a lit side and a shaded one,
so its block means differ by about as much as its pixels do. The layout gap is

    gap = sd(means of the b x b blocks) / sd(pixels)

on the grey image resized to ``side`` pixels (b = ``blocks`` per side). A stationary texture whose period is
below a block's side gives about 1 / (block side) for white noise and little more for a weave; a scene
gives 0.5-1. Measured on 64 px photo tiles (benchmarks/README.md, Thirty-ninth round): median over
classes 0.13 on the synthetic fabrics, 0.17 on the real ViTac cloth, 0.76 on vt60_subset's objects.
"""

from __future__ import annotations

import numpy as np
from PIL import Image

LAYOUT_SIDE = 64     # pixels the grey image is resized to
LAYOUT_BLOCKS = 4    # blocks per side (16 px each at 64 px)


def layout_gap(image: Image.Image, side: int = LAYOUT_SIDE, blocks: int = LAYOUT_BLOCKS) -> float:
    """sd of the ``blocks`` x ``blocks`` block means over sd of the pixels, on ``image`` in grey at ``side`` px;
    0 for a flat image (no layout to tell)."""
    grey = np.asarray(image.convert("L").resize((side, side), Image.BILINEAR), dtype=np.float64)
    spread = grey.std()
    if spread < 1e-6:
        return 0.0
    step = side // blocks
    means = grey[:step * blocks, :step * blocks].reshape(blocks, step, blocks, step).mean(axis=(1, 3))
    return float(means.std() / spread)
