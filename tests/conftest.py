"""Shared fixtures: paths, the real ViTac sample, and small image writers."""

from __future__ import annotations

import copy
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
VITAC = REPO.parent / "shared" / "data" / "vitac_cloth11"
VT60 = REPO.parent / "shared" / "data" / "vt60_subset"


# `make test` runs the tests on two workers that take one test file at a time, in collection order (the Makefile's
# pytest-xdist flags). The files below hold the end-to-end runs, the longest first (pytest --durations); they go first
# so that no long file starts last while the other worker idles.
LONGEST_FILES_FIRST = ("test_workflow.py", "test_cluster.py", "test_rerun.py", "test_nothing_silent.py",
                       "test_reliability.py", "test_studies.py", "test_report.py", "test_fuzz.py")


def pytest_collection_modifyitems(config, items):
    """Collection order: the files of LONGEST_FILES_FIRST in that order, then the others as collected."""
    rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: tests keep their order within a file


@pytest.fixture
def vt60_root() -> Path:
    """The real VT60 subset (10 objects, round-sensor grey touch frames and RGB photos, its authors' layout)."""
    if not VT60.is_dir():
        pytest.skip(f"real VT60 subset not found at {VT60}")
    return VT60


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
    params["translation"]["capacity"].update(widths=[4, 8], probe_iterations=4, eval_every=4, patience=1)
    params["translation"]["class_gan"]["iterations"] = None  # class pairs train the tiny preset's steps too
    params["recipes"]["fabric"]["translation.class_gan.iterations"] = None  # also where recipe auto picks fabric
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


def pair_tables(root, classes=("a", "b"), per_class=4, aligned=True):
    """A pairs folder as the pairs stage writes it, with random tiles on disk under ``root``."""
    rng = np.random.default_rng(1)
    rows, tiles = [], []
    for cls in classes:
        for i in range(per_class):
            split = "test" if i == 0 else "train"
            for modality in ("visual", "tactile"):
                path = f"tiles/{modality}/{cls}/{i}.png"
                write_image(root / path, rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
                tiles.append({"path": path, "class": cls, "modality": modality, "source": f"{cls}/{i}",
                              "group": f"{cls}/{i}", "split": split})
            rows.append({"direction": "v2t", "split": split, "class": cls, "input_path": f"tiles/visual/{cls}/{i}.png",
                         "target_path": f"tiles/tactile/{cls}/{i}.png", "input_source": f"{cls}/{i}",
                         "target_source": f"{cls}/{i}", "aligned": aligned,
                         "pair_kind": "pixel" if aligned else "class"})
    return pd.DataFrame(rows), pd.DataFrame(tiles)


def write_jpegs(root, count, side=96):
    """``count`` distinct JPEG files in the generic layout (two classes, both modalities)."""
    import cv2

    rng = np.random.default_rng(count)
    base = rng.integers(0, 256, (side, side, 3), dtype=np.uint8)
    for i in range(count):
        folder = root / f"c{i % 2}" / ("visual", "tactile")[(i // 2) % 2]
        folder.mkdir(parents=True, exist_ok=True)
        image = base.copy()
        image[0, 0] = i % 256, i // 256 % 256, 0  # distinct bytes per file
        cv2.imwrite(str(folder / f"s{i:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    return root
