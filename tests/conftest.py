"""Shared fixtures: paths, the real ViTac sample, and small image writers."""

from __future__ import annotations

import copy
import os
import shutil
import subprocess
import sys
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
    params["classify"].update(size=32, width=0.125, epochs=2, seeds=[0], batch_size=16)
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


BIN = str(Path(sys.executable).parent)
ENV = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "DVC_NO_ANALYTICS": "1"}


def make_project(where: Path, params: dict) -> Path:
    """A copy of the workflow files with ``params`` as its params.yaml."""
    where.mkdir(parents=True)
    for name in ("Snakefile", "dvc.yaml", ".dvcignore"):
        shutil.copy(REPO / name, where / name)
    for name in ("workflow", "src"):
        shutil.copytree(REPO / name, where / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    os.symlink(os.readlink(REPO / "profiles"), where / "profiles")  # where plain `snakemake` finds profiles/default
    (where / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return where


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True)
    assert result.returncode == 0, f"{' '.join(cmd)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="session")
def snakemake_project(tmp_path_factory):
    project = make_project(tmp_path_factory.mktemp("smk") / "project", tiny_params())
    result = run(["snakemake", "--cores", "2"], project)
    return project, result


