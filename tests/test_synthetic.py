"""Tests of the procedural ViTac-like synthetic dataset (vtgen.synthetic)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from vtgen.core.synthetic import FABRICS, Patch, render_gelsight, render_patch, render_visual
from vtgen.stages.render import render_dataset

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "vitac_cloth11"


def rng(*key: int) -> np.random.Generator:
    return np.random.default_rng(list(key))


def render_pair(fabric: str, size: int, key: int) -> tuple[Patch, np.ndarray, np.ndarray]:
    k = FABRICS.index(fabric)
    patch = render_patch(fabric, size, rng(key, k, 0))
    return patch, render_visual(patch, rng(key, k, 1)), render_gelsight(patch, rng(key, k, 2))


def band(x: np.ndarray, lo: float = 0.8, hi: float = 4.0) -> np.ndarray:
    """Difference-of-Gaussians band-pass: keeps yarn-scale structure."""
    x = x.astype(np.float32)
    return cv2.GaussianBlur(x, (0, 0), lo) - cv2.GaussianBlur(x, (0, 0), hi)


def marker_free(tactile: np.ndarray) -> np.ndarray:
    """Mask of pixels away from the dark marker dots."""
    g = tactile.astype(np.float32).mean(2)
    dark = (g < 0.55 * np.median(g)).astype(np.uint8)
    return cv2.dilate(dark, np.ones((9, 9), np.uint8)) == 0


def find_markers(tactile: np.ndarray) -> np.ndarray:
    """Centroids (x, y) of dark blobs of at least 20 pixels."""
    g = tactile.astype(np.float32).mean(2)
    dark = (g < 0.55 * np.median(g)).astype(np.uint8)
    _, _, stats, centroids = cv2.connectedComponentsWithStats(dark, connectivity=8)
    return centroids[1:][stats[1:, cv2.CC_STAT_AREA] >= 20]


def read_rgb(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    return img[..., ::-1]


# --------------------------------------------------------------------------- contract


def test_fabric_names() -> None:
    assert FABRICS == (
        "plain_weave", "twill_2_1", "twill_3_1", "satin", "basket_weave", "rib_knit",
        "jersey_knit", "denim", "corduroy", "herringbone", "felt", "printed",
    )


@pytest.mark.parametrize("fabric", FABRICS)
def test_patch_and_images_have_the_contracted_shapes_and_ranges(fabric: str) -> None:
    patch, visual, tactile = render_pair(fabric, 48, key=1)
    assert patch.height.shape == (48, 48) and patch.height.dtype == np.float32
    assert patch.albedo.shape == (48, 48, 3) and patch.albedo.dtype == np.float32
    assert patch.height.min() >= 0.0 and patch.height.max() <= 1.0
    assert patch.albedo.min() >= 0.0 and patch.albedo.max() <= 1.0
    assert patch.height.std() > 0.05  # real relief, not a flat field
    for img in (visual, tactile):
        assert img.shape == (48, 48, 3) and img.dtype == np.uint8
        assert img.std() > 2.0


def test_renderers_keep_the_shape_of_a_non_square_patch() -> None:
    patch = render_patch("twill_2_1", 80, rng(0))
    strip = Patch(patch.height[:48], patch.albedo[:48])
    assert render_visual(strip, rng(1)).shape == (48, 80, 3)
    assert render_gelsight(strip, rng(1)).shape == (48, 80, 3)


def test_same_seed_gives_identical_arrays_and_another_seed_differs() -> None:
    for fabric in ("denim", "felt", "printed"):
        a, b, c = (render_pair(fabric, 64, key) for key in (5, 5, 6))
        assert np.array_equal(a[0].height, b[0].height) and np.array_equal(a[0].albedo, b[0].albedo)
        assert np.array_equal(a[1], b[1]) and np.array_equal(a[2], b[2])
        assert not np.array_equal(a[0].height, c[0].height)
        assert not np.array_equal(a[1], c[1]) and not np.array_equal(a[2], c[2])


def test_unknown_fabric_and_tiny_size_are_rejected() -> None:
    with pytest.raises(ValueError, match="velvet"):
        render_patch("velvet", 64, rng(0))
    with pytest.raises(ValueError, match="16"):
        render_patch("denim", 15, rng(0))
    render_patch("denim", 16, rng(0))  # the smallest allowed size works


# --------------------------------------------------------------------------- the classes are distinct


def radial_spectrum(img: np.ndarray, bins: int = 10) -> np.ndarray:
    """Log of the radially averaged power spectrum."""
    f = img - img.mean()
    power = np.abs(np.fft.fftshift(np.fft.fft2(f))) ** 2
    n = img.shape[0]
    y, x = np.mgrid[:n, :n] - n // 2
    idx = np.digitize(np.hypot(x, y).ravel(), np.linspace(1, n // 2, bins + 1)) - 1
    ok = (idx >= 0) & (idx < bins)
    total = np.bincount(idx[ok], power.ravel()[ok], bins)
    return np.log(total / np.maximum(np.bincount(idx[ok], None, bins), 1) + 1e-9)


def tactile_features(tactile: np.ndarray) -> np.ndarray:
    """Relief spectrum, gradient-orientation histogram and contrast of a GelSight image, markers blanked."""
    g = tactile.astype(np.float32).mean(2)
    keep = marker_free(tactile)
    b = band(np.where(keep, g, np.median(g[keep])), 0.7, 6.0)
    gx, gy = cv2.Sobel(b, cv2.CV_32F, 1, 0), cv2.Sobel(b, cv2.CV_32F, 0, 1)
    angle = np.minimum((np.arctan2(gy, gx) % np.pi / np.pi * 8).astype(int), 7)
    hist = np.bincount(angle.ravel(), np.hypot(gx, gy).ravel(), 8)
    return np.concatenate([radial_spectrum(b), 10 * hist / hist.sum(), [np.log(b.std())]])


def nearest_centroid_accuracy(features: np.ndarray, labels: np.ndarray, train: np.ndarray) -> float:
    mu, sd = features[train].mean(0), features[train].std(0) + 1e-9
    z = (features - mu) / sd
    centroids = np.stack([z[train & (labels == k)].mean(0) for k in range(len(FABRICS))])
    pred = np.argmin(((z[~train][:, None] - centroids[None]) ** 2).sum(-1), 1)
    return float((pred == labels[~train]).mean())


@pytest.mark.slow
def test_classes_are_distinct_for_a_nearest_centroid_classifier() -> None:
    per_class, n_train = 9, 6
    visual_f, tactile_f, labels = [], [], []
    for k, fabric in enumerate(FABRICS):
        for j in range(per_class):
            patch, visual, tactile = render_pair(fabric, 64, key=100 + j)
            visual_f.append(np.concatenate([visual.reshape(-1, 3).mean(0) / 255.0, radial_spectrum(patch.height)]))
            tactile_f.append(tactile_features(tactile))
            labels.append(k)
    labels_a = np.array(labels)
    train = np.tile(np.arange(per_class) < n_train, len(FABRICS))
    chance = 1 / len(FABRICS)
    # mean colour + relief spectrum: measured 0.83 on these seeds
    assert nearest_centroid_accuracy(np.array(visual_f), labels_a, train) >= 0.6
    # tactile alone (no colour: the gel looks the same for every cloth): measured 0.50
    assert nearest_centroid_accuracy(np.array(tactile_f), labels_a, train) >= 4 * chance


# --------------------------------------------------------------------------- GelSight look


def test_tactile_ignores_colour_and_print() -> None:
    patch = render_patch("printed", 64, rng(3))
    grey = Patch(patch.height, np.full_like(patch.albedo, 0.5))
    assert np.array_equal(render_gelsight(patch, rng(4)), render_gelsight(grey, rng(4)))
    assert not np.array_equal(render_visual(patch, rng(4)), render_visual(grey, rng(4)))


@pytest.mark.parametrize("fabric", FABRICS)
def test_gel_background_shows_where_the_relief_is_low(fabric: str) -> None:
    patch = render_patch(fabric, 96, rng(1, FABRICS.index(fabric)))
    flat = Patch(np.zeros_like(patch.height), patch.albedo)
    pressed = render_gelsight(patch, rng(5)).astype(np.float32)
    untouched = render_gelsight(flat, rng(5)).astype(np.float32)  # same gel, lights, markers, noise
    change = np.abs(pressed - untouched).mean(2)
    relief = cv2.GaussianBlur(patch.height, (0, 0), 2.0)
    low = relief <= np.percentile(relief, 10)
    high = relief >= np.percentile(relief, 90)
    assert change[low].mean() < 6.0  # measured 1-4.5 levels
    assert change[high].mean() > 2 * change[low].mean()  # measured 2.5-8 times


def test_flat_gel_has_the_gelsight_background_colour() -> None:
    flat = Patch(np.zeros((128, 128), np.float32), np.zeros((128, 128, 3), np.float32))
    img = render_gelsight(flat, rng(0))
    r, g, b = np.median(img.reshape(-1, 3), 0)
    assert r > b > g  # the mauve of the ViTac gel: red light strongest, green weakest
    assert 100 <= g and r <= 170


@pytest.mark.parametrize("fabric", ["plain_weave", "corduroy", "felt", "denim"])
def test_tactile_has_dark_marker_dots_on_a_regular_grid(fabric: str) -> None:
    _, _, tactile = render_pair(fabric, 256, key=2)
    centres = find_markers(tactile)
    assert len(centres) >= 6
    dist = np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1))
    np.fill_diagonal(dist, np.inf)
    nearest = dist.min(1)
    assert nearest.std() / nearest.mean() < 0.1  # regular spacing (real ViTac tiles: 0.02-0.05)
    assert 55 < np.median(nearest) < 80  # about 65 px at 256 px, like the real tiles
    g = tactile.astype(np.float32).mean(2)
    for x, y in centres.round().astype(int):  # each dot is a dark local minimum
        assert g[y, x] < 0.6 * np.median(g)


@pytest.mark.skipif(not REAL.is_dir(), reason="real ViTac sample not available")
def test_tactile_statistics_are_close_to_the_real_gelsight_tiles() -> None:
    def highpass(img: np.ndarray) -> float:
        f = img.astype(np.float32)
        return float(np.abs(f - cv2.GaussianBlur(f, (0, 0), 4)).mean())

    real = [read_rgb(p) for p in sorted((REAL / "11t").glob("*.jpg"))]
    synth = [render_pair(f, 256, key=9)[2] for f in FABRICS]
    real_mean = np.mean([r.reshape(-1, 3).mean(0) for r in real], 0)
    synth_mean = np.mean([s.reshape(-1, 3).mean(0) for s in synth], 0)
    assert np.abs(real_mean - synth_mean).max() < 12  # measured < 1 level
    real_hp, synth_hp = np.mean([highpass(r) for r in real]), np.mean([highpass(s) for s in synth])
    assert 0.6 < synth_hp / real_hp < 1.5  # texture contrast, measured 8.7 vs 9.4
    real_count = np.mean([len(find_markers(r)) for r in real])
    synth_count = np.mean([len(find_markers(s)) for s in synth])
    assert abs(real_count - synth_count) < 4


# --------------------------------------------------------------------------- print is independent of relief


def test_printed_colour_varies_far_more_than_its_relief_explains() -> None:
    def ratio(fabric: str) -> float:
        out = []
        for key in range(4):
            _, visual, tactile = render_pair(fabric, 96, key=30 + key)
            keep = marker_free(tactile)
            out.append(visual.reshape(-1, 3).astype(np.float32).var(0).sum()
                       / tactile[keep].astype(np.float32).var(0).sum())
        return float(np.mean(out))

    # same plain weave underneath; the print adds colour the gel cannot feel
    assert ratio("printed") > 5 * ratio("plain_weave")


# --------------------------------------------------------------------------- render_dataset


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*.png"))}


def test_aligned_dataset_layout_json_and_atomic_replace(tmp_path: Path) -> None:
    out = tmp_path / "synthetic"
    out.mkdir()
    (out / "stale.txt").write_text("from an older run")
    stale_tmp = tmp_path / ".synthetic.tmp"
    stale_tmp.mkdir()
    (stale_tmp / "half.png").write_text("killed run")

    info = render_dataset(out, ["denim", "felt"], 3, 32, aligned=True, seed=7, workers=1, progress=False)

    assert not stale_tmp.exists() and not (tmp_path / ".synthetic.old").exists()
    assert not (out / "stale.txt").exists()
    written = json.loads((out / "dataset.json").read_text())
    assert written == {"synthetic": True, "generator": "vtgen.synthetic", "aligned": True, "seed": 7,
                       "size": 32, "samples_per_class": 3, "classes": ["denim", "felt"]}
    assert info["seconds"] >= 0 and {k: v for k, v in info.items() if k != "seconds"} == written
    assert sorted(p.name for p in out.iterdir()) == ["dataset.json", "denim", "felt"]
    for c in ("denim", "felt"):
        names = [f"s{i:04d}.png" for i in range(3)]
        assert sorted(p.name for p in (out / c / "visual").iterdir()) == names
        assert sorted(p.name for p in (out / c / "tactile").iterdir()) == names
        img = cv2.imread(str(out / c / "visual" / "s0000.png"), cv2.IMREAD_UNCHANGED)
        assert img.shape == (32, 32, 3) and img.dtype == np.uint8


def test_png_files_are_rgb_in_the_right_channel_order(tmp_path: Path) -> None:
    render_dataset(tmp_path / "d", ["denim"], 1, 32, aligned=True, seed=0, workers=1, progress=False)
    rgb = read_rgb(tmp_path / "d" / "denim" / "tactile" / "s0000.png")
    seed_seq = np.random.SeedSequence([0, FABRICS.index("denim"), 0]).spawn(4)
    patch = render_patch("denim", 32, np.random.default_rng(seed_seq[0]))
    assert np.array_equal(rgb, render_gelsight(patch, np.random.default_rng(seed_seq[3])))


@pytest.mark.slow
def test_one_and_two_workers_write_identical_files(tmp_path: Path) -> None:
    args = dict(classes=["plain_weave", "printed", "rib_knit"], samples_per_class=4, size=32, seed=3,
                progress=False)
    render_dataset(tmp_path / "one", aligned=True, workers=1, **args)
    render_dataset(tmp_path / "two", aligned=True, workers=2, **args)
    one, two = files(tmp_path / "one"), files(tmp_path / "two")
    assert len(one) == 3 * 4 * 2 and one == two


def test_other_seed_gives_other_files(tmp_path: Path) -> None:
    args = dict(classes=["satin"], samples_per_class=2, size=32, aligned=True, workers=1, progress=False)
    render_dataset(tmp_path / "a", seed=1, **args)
    render_dataset(tmp_path / "b", seed=2, **args)
    a, b = files(tmp_path / "a"), files(tmp_path / "b")
    assert a.keys() == b.keys() and all(a[k] != b[k] for k in a)


def test_unaligned_names_never_match_and_images_come_from_other_patches(tmp_path: Path) -> None:
    classes = ["jersey_knit", "corduroy"]
    render_dataset(tmp_path / "u", classes, 3, 32, aligned=False, seed=0, workers=1, progress=False)
    render_dataset(tmp_path / "a", classes, 3, 32, aligned=True, seed=0, workers=1, progress=False)
    assert json.loads((tmp_path / "u" / "dataset.json").read_text())["aligned"] is False
    for c in classes:
        visual = sorted(p.stem for p in (tmp_path / "u" / c / "visual").iterdir())
        tactile = sorted(p.stem for p in (tmp_path / "u" / c / "tactile").iterdir())
        assert visual == ["v0000", "v0001", "v0002"] and tactile == ["t0000", "t0001", "t0002"]
        assert not set(visual) & set(tactile)
        # the visual is the aligned sample's visual; the tactile is of another patch
        assert (tmp_path / "u" / c / "visual" / "v0000.png").read_bytes() == \
            (tmp_path / "a" / c / "visual" / "s0000.png").read_bytes()
        assert (tmp_path / "u" / c / "tactile" / "t0000.png").read_bytes() != \
            (tmp_path / "a" / c / "tactile" / "s0000.png").read_bytes()


def relief_r2(visual: np.ndarray, tactile: np.ndarray) -> float:
    """Share of the visual's yarn-scale structure explained linearly by the tactile channels."""
    keep = marker_free(tactile)
    y = band(visual.astype(np.float32).mean(2))[keep]
    x = np.stack([band(tactile[..., c])[keep] for c in range(3)] + [np.ones(keep.sum(), np.float32)], 1)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    return float(1 - (y - x @ coef).var() / y.var())


def test_aligned_visual_and_tactile_share_one_relief(tmp_path: Path) -> None:
    classes = ["plain_weave", "twill_2_1", "rib_knit", "jersey_knit", "felt"]
    render_dataset(tmp_path / "a", classes, 2, 128, aligned=True, seed=0, workers=1, progress=False)
    for c in classes:
        root = tmp_path / "a" / c
        visual = read_rgb(root / "visual" / "s0000.png")
        same = relief_r2(visual, read_rgb(root / "tactile" / "s0000.png"))
        other = relief_r2(visual, read_rgb(root / "tactile" / "s0001.png"))
        assert same > 0.1 and same > 5 * other, (c, same, other)  # measured 0.12-0.42 vs <= 0.02


def test_bad_arguments_raise_and_write_nothing(tmp_path: Path) -> None:
    out = tmp_path / "d"
    with pytest.raises(ValueError, match="plain_weave"):  # the message lists the valid names
        render_dataset(out, ["denim", "velvet"], 1, 32, aligned=True, seed=0, progress=False)
    with pytest.raises(ValueError):
        render_dataset(out, ["denim"], 1, 8, aligned=True, seed=0, progress=False)
    with pytest.raises(ValueError):
        render_dataset(out, ["denim"], 0, 32, aligned=True, seed=0, progress=False)
    assert list(tmp_path.iterdir()) == []
