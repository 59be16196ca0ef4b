"""Shared fixtures: paths, the real ViTac sample, and small image writers."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
VITAC = REPO.parent / "shared" / "data" / "vitac_cloth11"


@pytest.fixture
def vitac_root() -> Path:
    if not VITAC.is_dir():
        pytest.skip(f"real ViTac sample not found at {VITAC}")
    return VITAC


@pytest.fixture
def default_params() -> dict:
    return yaml.safe_load((REPO / "params.yaml").read_text())


TINY_MODEL = dict(size=32, ngf=8, ndf=8, kernel=4, discriminator="patch", patch_layers=2, batch_size=2, iterations=10)


def tiny_params(**overrides) -> dict:
    """params.yaml with small settings for end-to-end tests; ``overrides`` replace whole sections' keys."""
    params = copy.deepcopy(yaml.safe_load((REPO / "params.yaml").read_text()))
    params["synthetic"].update(classes=["plain_weave", "denim", "felt"], samples_per_class=6, size=64, workers=2)
    params["roi"].update(size=32)
    params["presets"]["fast"].update(TINY_MODEL)
    params["translation"].update(checkpoint_every=5, log_every=2)
    params["generate"].update(batch_size=8)
    for section, values in overrides.items():
        params[section].update(values)
    return params


def write_image(path: Path, array: np.ndarray, convert: str | None = None) -> Path:
    """Save ``array`` with Pillow (2-D uint8 -> L, 2-D uint16 -> I;16, 4 channels -> RGBA); optionally convert first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    image = Image.fromarray(array)
    (image.convert(convert) if convert else image).save(path)
    return path


def random_rgb(rng: np.random.Generator, size: int = 32) -> np.ndarray:
    return rng.integers(0, 256, (size, size, 3), dtype=np.uint8)
