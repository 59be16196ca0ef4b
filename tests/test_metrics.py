"""vtgen.core.metrics against scikit-image, at the extremes, and on bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from vtgen.core import metrics
from vtgen.core.metrics import colour_ssim, grey_ssim, pairwise_colour_ssim, psnr

C1_255 = (0.01 * 255) ** 2
LUMA = np.array([0.299, 0.587, 0.114])


def skimage_ssim(x: np.ndarray, y: np.ndarray, data_range: float = 255.0) -> float:
    """The reference: Wang et al. settings, float64, channels last (2-D images: one channel)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    channel_axis = -1 if x.ndim == 3 and x.shape[-1] > 1 else None
    if x.ndim == 3 and x.shape[-1] == 1:
        x, y = x[..., 0], y[..., 0]
    return structural_similarity(x, y, channel_axis=channel_axis, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, data_range=data_range)


def noisy(rng: np.random.Generator, image: np.ndarray, sd: float) -> np.ndarray:
    return np.clip(image + rng.normal(0, sd, image.shape), 0, 255).round().astype(np.uint8)


def gradient(height: int, width: int) -> np.ndarray:
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    return (255 * np.stack([xx, yy, (xx + yy) / 2], axis=-1)).round().astype(np.uint8)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20190520)


@pytest.fixture
def image_pairs(rng) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    random = rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)
    smooth = gradient(64, 80)
    return {
        "random vs random": (random, rng.integers(0, 256, (64, 64, 3), dtype=np.uint8)),
        "random vs noisy copy": (random, noisy(rng, random, 25)),
        "gradient vs noisy copy": (smooth, noisy(rng, smooth, 8)),
        "gradient vs flipped": (smooth, smooth[::-1].copy()),
        "binary 0/255": (255 * rng.integers(0, 2, (40, 33, 3), dtype=np.uint8),
                         255 * rng.integers(0, 2, (40, 33, 3), dtype=np.uint8)),
    }


# ---------------------------------------------------------------------------------------------
# agreement with scikit-image


def test_colour_ssim_matches_skimage(image_pairs):
    for name, (x, y) in image_pairs.items():
        expected = skimage_ssim(x, y)
        assert colour_ssim(x, y) == pytest.approx(expected, abs=1e-12), name
        as_float = colour_ssim(x.astype(np.float64), y.astype(np.float64), data_range=255)
        assert as_float == pytest.approx(expected, abs=1e-12)


def test_colour_ssim_batch_matches_skimage_per_image(rng):
    x = rng.integers(0, 256, (5, 48, 56, 3), dtype=np.uint8)
    y = noisy(rng, x, 30)
    expected = [skimage_ssim(x[i], y[i]) for i in range(5)]
    scores = colour_ssim(x, y)
    assert scores.shape == (5,) and scores.dtype == np.float64
    np.testing.assert_allclose(scores, expected, rtol=0, atol=1e-12)


def test_colour_ssim_float_images_in_unit_range(rng):
    x = rng.random((30, 45, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    assert colour_ssim(x, y, data_range=1.0) == pytest.approx(skimage_ssim(x, y, data_range=1.0), abs=1e-12)


def test_single_channel_matches_skimage_2d(rng):
    x = rng.integers(0, 256, (32, 27, 1), dtype=np.uint8)
    y = noisy(rng, x, 20)
    assert colour_ssim(x, y) == pytest.approx(skimage_ssim(x, y), abs=1e-12)


def test_grey_ssim_is_ssim_of_bt601_luma(image_pairs):
    for name, (x, y) in image_pairs.items():
        expected = structural_similarity(x @ LUMA, y @ LUMA, gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=255)
        assert grey_ssim(x, y) == pytest.approx(expected, abs=1e-12), name


def test_psnr_matches_skimage(image_pairs):
    for name, (x, y) in image_pairs.items():
        assert psnr(x, y) == pytest.approx(peak_signal_noise_ratio(x, y, data_range=255), rel=1e-12), name
    x, y = image_pairs["random vs noisy copy"]
    xf, yf = x / 255.0, y / 255.0
    assert psnr(xf, yf, data_range=1.0) == pytest.approx(peak_signal_noise_ratio(xf, yf, data_range=1.0), rel=1e-12)


def test_psnr_of_identical_images_is_inf(rng):
    x = rng.integers(0, 256, (3, 16, 16, 3), dtype=np.uint8)
    scores = psnr(x, x)
    assert scores.shape == (3,) and np.all(np.isposinf(scores))
    assert psnr(x[0], x[0]) == np.inf


@settings(max_examples=25, deadline=None)
@given(st.data())
def test_property_colour_ssim_bounded_and_equal_to_skimage(data):
    height = data.draw(st.integers(11, 24), label="height")
    width = data.draw(st.integers(11, 24), label="width")
    channels = data.draw(st.sampled_from([1, 3]), label="channels")
    shape = (height, width, channels)
    x = data.draw(arrays(np.uint8, shape), label="x")
    y = data.draw(arrays(np.uint8, shape), label="y")
    score = colour_ssim(x, y)
    assert -1.0 <= score <= 1.0
    assert score == pytest.approx(skimage_ssim(x, y), abs=1e-10)


@settings(max_examples=25, deadline=None)
@given(arrays(np.uint8, (12, 13, 3)), arrays(np.uint8, (12, 13, 3)))
def test_property_symmetric_and_psnr_matches_skimage(x, y):
    assert colour_ssim(x, y) == colour_ssim(y, x)
    expected = peak_signal_noise_ratio(x, y, data_range=255) if (x != y).any() else np.inf
    assert psnr(x, y) == pytest.approx(expected, rel=1e-12)


# ---------------------------------------------------------------------------------------------
# stability at the extremes (values documented in colour_ssim's Notes)


def test_identical_images_score_exactly_one(rng, image_pairs):
    for x, _ in image_pairs.values():
        assert colour_ssim(x, x) == 1.0
        assert grey_ssim(x, x) == 1.0
    x = rng.random((4, 20, 20, 3))
    np.testing.assert_array_equal(colour_ssim(x, x, data_range=1.0), 1.0)


def test_equal_constant_images_score_one():
    for value in (0, 1, 128, 255):
        x = np.full((16, 16, 3), value, np.uint8)
        assert colour_ssim(x, x) == 1.0
    x = np.full((16, 16, 3), 0.37)
    assert colour_ssim(x, x, data_range=1.0) == 1.0


@pytest.mark.parametrize("c1, c2", [(0, 255), (255, 0), (10, 200), (100, 101), (0, 1)])
def test_constant_images_follow_the_luminance_formula(c1, c2):
    x = np.full((2, 16, 20, 3), c1, np.uint8)
    y = np.full((2, 16, 20, 3), c2, np.uint8)
    expected = (2 * c1 * c2 + C1_255) / (c1**2 + c2**2 + C1_255)
    np.testing.assert_allclose(colour_ssim(x, y), expected, rtol=1e-12)
    assert colour_ssim(x[0], y[0]) == pytest.approx(skimage_ssim(x[0], y[0]), abs=1e-12)


def test_black_against_white_is_about_1e_minus_4():
    black = np.zeros((32, 32, 3), np.uint8)
    white = np.full((32, 32, 3), 255, np.uint8)
    score = colour_ssim(black, white)
    assert np.isfinite(score) and -1 <= score <= 1
    assert score == pytest.approx(6.5025 / 65031.5025, rel=1e-12)
    assert score == pytest.approx(9.99900e-5, rel=1e-5)


def test_zero_variance_against_texture_is_finite(rng):
    flat = np.full((24, 24, 3), 128, np.uint8)
    texture = rng.integers(0, 256, (24, 24, 3), dtype=np.uint8)
    score = colour_ssim(flat, texture)
    assert np.isfinite(score) and -1 <= score <= 1
    assert score == pytest.approx(skimage_ssim(flat, texture), abs=1e-12)


def test_nearly_flat_images_match_skimage(rng):
    # variances of order 1e-18: rounding could push E[x^2] - mu^2 below zero; C2 keeps it harmless
    x = np.full((20, 20, 3), 0.3)
    y = x.copy()
    y[7, 9, 1] += 1e-9
    for a, b in [(x, y), (y, x), (x + rng.normal(0, 1e-12, x.shape), y)]:
        score = colour_ssim(a, b, data_range=1.0)
        assert np.isfinite(score) and -1 <= score <= 1
        assert score == pytest.approx(skimage_ssim(a, b, data_range=1.0), abs=1e-12)


def test_extreme_data_range_values_stay_finite(rng):
    x = rng.random((20, 20, 3)) * 1e6
    y = x + rng.normal(0, 1e3, x.shape)
    assert colour_ssim(x, y, data_range=2e6) == pytest.approx(skimage_ssim(x, y, data_range=2e6), abs=1e-10)
    tiny = rng.random((20, 20, 3)) * 1e-6
    assert colour_ssim(tiny, tiny[::-1].copy(), data_range=1e-6) == pytest.approx(
        skimage_ssim(tiny, tiny[::-1], data_range=1e-6), abs=1e-10)


# ---------------------------------------------------------------------------------------------
# dtypes and data_range


def test_uint8_equals_float_with_the_same_values(image_pairs):
    for name, (x, y) in image_pairs.items():
        f64, f32 = (x.astype(np.float64), y.astype(np.float64)), (x.astype(np.float32), y.astype(np.float32))
        assert colour_ssim(x, y) == pytest.approx(colour_ssim(*f64, 255), abs=1e-12)
        assert colour_ssim(x, y) == pytest.approx(colour_ssim(x / 255.0, y / 255.0, data_range=1.0), abs=1e-9), name
        assert grey_ssim(x, y) == pytest.approx(grey_ssim(x / 255.0, y / 255.0, data_range=1.0), abs=1e-9)
        assert psnr(x, y) == pytest.approx(psnr(x / 255.0, y / 255.0, data_range=1.0), rel=1e-9)
        assert colour_ssim(x, y) == pytest.approx(colour_ssim(*f32, 255), abs=1e-12)


@pytest.mark.parametrize("metric", [colour_ssim, grey_ssim, psnr, pairwise_colour_ssim])
def test_float_input_needs_data_range(metric, rng):
    x = rng.random((16, 16, 3))
    with pytest.raises(ValueError, match="data_range"):
        metric(x, x)
    with pytest.raises(ValueError, match="data_range"):
        metric(x, (x * 255).astype(np.uint8))


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), float("inf")])
def test_data_range_must_be_positive_and_finite(bad):
    x = np.zeros((16, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="data_range"):
        colour_ssim(x, x, data_range=bad)


@pytest.mark.parametrize("value, message", [(np.nan, "NaN"), (np.inf, "infinite"), (-np.inf, "infinite")])
@pytest.mark.parametrize("metric", [colour_ssim, grey_ssim, psnr, pairwise_colour_ssim])
def test_non_finite_input_is_refused(metric, value, message):
    x = np.zeros((16, 16, 3))
    y = x.copy()
    y[3, 4, 1] = value
    with pytest.raises(ValueError, match=message):
        metric(x, y, data_range=1.0)
    with pytest.raises(ValueError, match=message):
        metric(y, x, data_range=1.0)


# ---------------------------------------------------------------------------------------------
# shapes


def test_mismatched_and_malformed_shapes_are_refused():
    x = np.zeros((16, 16, 3), np.uint8)
    cases = [
        (x, np.zeros((16, 17, 3), np.uint8), r"\(16, 16, 3\) and \(16, 17, 3\)"),
        (x, x[None], r"\(16, 16, 3\) and \(1, 16, 16, 3\)"),
        (x[..., 0], x[..., 0], r"\(16, 16\)"),
        (x[None, None], x[None, None], r"\(1, 1, 16, 16, 3\)"),
        (np.zeros((16, 16, 4), np.uint8), np.zeros((16, 16, 4), np.uint8), r"\(16, 16, 4\)"),
        (np.zeros((16, 16, 2), np.uint8), np.zeros((16, 16, 2), np.uint8), r"\(16, 16, 2\)"),
    ]
    for a, b, message in cases:
        for metric in (colour_ssim, grey_ssim, psnr):
            with pytest.raises(ValueError, match=message):
                metric(a, b)
    with pytest.raises(ValueError, match=r"\(16, 16, 1\)"):
        grey_ssim(x[..., :1], x[..., :1])
    with pytest.raises(ValueError, match="dtype"):
        colour_ssim(x.astype(bool), x.astype(bool), data_range=1)


def test_images_smaller_than_the_window_are_refused():
    for shape in [(10, 20, 3), (20, 10, 3), (4, 10, 10, 3)]:
        x = np.zeros(shape, np.uint8)
        with pytest.raises(ValueError, match=r"smaller than the 11x11 Gaussian window of SSIM"):
            colour_ssim(x, x)
        with pytest.raises(ValueError, match=r"smaller than the 11x11"):
            grey_ssim(x, x)
    x = np.zeros((10, 20, 3), np.uint8)
    with pytest.raises(ValueError, match=r"image is 10x20"):
        pairwise_colour_ssim(x, x)


def test_window_sized_image_has_one_valid_position(rng):
    x = rng.integers(0, 256, (11, 11, 3), dtype=np.uint8)
    y = noisy(rng, x, 40)
    assert colour_ssim(x, y) == pytest.approx(skimage_ssim(x, y), abs=1e-12)


def test_batch_equals_single_images_and_single_is_0d(rng):
    x = rng.integers(0, 256, (4, 24, 30, 3), dtype=np.uint8)
    y = noisy(rng, x, 15)
    for metric in (colour_ssim, grey_ssim, psnr):
        batch = metric(x, y)
        singles = [metric(x[i], y[i]) for i in range(4)]
        assert batch.shape == (4,) and all(s.shape == () and s.dtype == np.float64 for s in singles)
        np.testing.assert_allclose(batch, singles, rtol=0, atol=1e-13)
    assert colour_ssim(x[:0], y[:0]).shape == (0,)


def test_large_batch_matches_skimage(rng):
    x = rng.integers(0, 256, (70, 12, 12, 3), dtype=np.uint8)
    y = noisy(rng, x, 50)
    scores = colour_ssim(x, y)
    np.testing.assert_allclose(scores[[0, 33, 69]], [skimage_ssim(x[i], y[i]) for i in (0, 33, 69)], atol=1e-12)


def test_torch_tensors_are_accepted(rng):
    x = rng.integers(0, 256, (2, 20, 20, 3), dtype=np.uint8)
    y = noisy(rng, x, 20)
    expected = colour_ssim(x, y)
    np.testing.assert_array_equal(colour_ssim(torch.from_numpy(x), torch.from_numpy(y)), expected)
    tx = torch.from_numpy(x).double().requires_grad_()
    np.testing.assert_allclose(colour_ssim(tx, torch.from_numpy(y).double(), data_range=255), expected, atol=1e-12)
    assert isinstance(psnr(torch.from_numpy(x), torch.from_numpy(y)), np.ndarray)


def test_non_contiguous_and_big_endian_arrays(rng):
    x = rng.integers(0, 256, (30, 30, 3), dtype=np.uint8)
    y = noisy(rng, x, 20)
    flipped = x[::-1, ::2]
    assert colour_ssim(flipped, y[::-1, ::2]) == pytest.approx(skimage_ssim(flipped, y[::-1, ::2]), abs=1e-12)
    big = x.astype(">f8")
    assert colour_ssim(big, y.astype(">f8"), data_range=255) == pytest.approx(colour_ssim(x, y), abs=1e-12)


def test_ssim_is_symmetric(image_pairs):
    for x, y in image_pairs.values():
        assert colour_ssim(x, y) == colour_ssim(y, x)
        assert grey_ssim(x, y) == grey_ssim(y, x)


# ---------------------------------------------------------------------------------------------
# set-to-set


def test_pairwise_equals_the_loop_over_pairs(rng):
    a = rng.integers(0, 256, (3, 24, 28, 3), dtype=np.uint8)
    b = np.concatenate([noisy(rng, a, 20), rng.integers(0, 256, (2, 24, 28, 3), dtype=np.uint8)])
    loop = np.array([[colour_ssim(a[i], b[j]) for j in range(len(b))] for i in range(len(a))])
    for batch_size in (1, 2, 256):
        matrix = pairwise_colour_ssim(a, b, batch_size=batch_size)
        assert matrix.shape == (3, 5) and matrix.dtype == np.float64
        np.testing.assert_allclose(matrix, loop, rtol=0, atol=1e-13)
    np.testing.assert_allclose(pairwise_colour_ssim(b, a), loop.T, rtol=0, atol=1e-13)
    np.testing.assert_allclose(pairwise_colour_ssim(a / 255.0, b / 255.0, data_range=1.0), loop, atol=1e-9)
    assert pairwise_colour_ssim(a[0], b).shape == (1, 5)
    np.testing.assert_array_equal(np.diag(pairwise_colour_ssim(a, a)), 1.0)


def test_pairwise_shapes(rng):
    a = rng.integers(0, 256, (2, 16, 16, 3), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"\(2, 16, 16, 3\) and \(2, 16, 17, 3\)"):
        pairwise_colour_ssim(a, np.zeros((2, 16, 17, 3), np.uint8))
    with pytest.raises(ValueError, match="batch_size"):
        pairwise_colour_ssim(a, a, batch_size=0)
    assert pairwise_colour_ssim(a, a[:0]).shape == (2, 0)


# ---------------------------------------------------------------------------------------------
# the fused float64 kernel (numba), the one SSIM implementation


def extreme_pairs(height: int, width: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """uint8 (H, W, 3) pairs at the extremes: halves, checkerboards, constants."""
    yy, xx = np.mgrid[0:height, 0:width]
    halves = np.where(xx < width // 2, 0, 255).astype(np.uint8)[..., None].repeat(3, axis=-1)
    across = np.where(yy < height // 2, 255, 0).astype(np.uint8)[..., None].repeat(3, axis=-1)
    pixels = ((yy + xx) % 2 * 255).astype(np.uint8)[..., None].repeat(3, axis=-1)
    blocks = ((yy // 4 + xx // 3) % 2 * 255).astype(np.uint8)
    blocks = np.stack([blocks, 255 - blocks, blocks // 2], axis=-1)
    return {
        "black/white halves": (halves, across),
        "halves vs shifted halves": (halves, np.roll(halves, 1, axis=1)),
        "pixel checkerboard vs its negative": (pixels, 255 - pixels),
        "pixel checkerboard vs block checkerboard": (pixels, blocks),
        "checkerboard vs grey": (blocks, np.full_like(blocks, 128)),
        "black vs white": (np.zeros_like(halves), np.full_like(halves, 255)),
    }


@pytest.mark.parametrize("height, width", [(11, 11), (12, 13), (13, 11), (15, 40), (75, 67), (139, 21)])
def test_kernel_matches_skimage_on_odd_sizes_and_extremes(rng, height, width):
    # 139 rows: three bands of output rows (64, 64, 1) and partial blocks of 4 rows
    pairs = extreme_pairs(height, width)
    random = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
    pairs["random vs noisy copy"] = (random, noisy(rng, random, 30))
    pairs["gradient vs noisy copy"] = (gradient(height, width), noisy(rng, gradient(height, width), 10))
    for name, (x, y) in pairs.items():
        expected = skimage_ssim(x, y)
        assert colour_ssim(x, y) == pytest.approx(expected, abs=1e-12), name
        assert colour_ssim(x / 255.0, y / 255.0, data_range=1.0) == pytest.approx(
            skimage_ssim(x / 255.0, y / 255.0, data_range=1.0), abs=1e-12), name


def test_kernel_on_real_looking_images(rng):
    x = gradient(96, 128).astype(np.float64)
    x += 40 * np.sin(np.arange(128) / 3.0)[None, :, None] * np.cos(np.arange(96) / 5.0)[:, None, None]
    x = np.clip(x, 0, 255).round().astype(np.uint8)
    for y in (noisy(rng, x, 12), np.roll(x, 2, axis=0), (x * 0.8 + 20).astype(np.uint8), x[:, ::-1]):
        assert colour_ssim(x, y) == pytest.approx(skimage_ssim(x, y), abs=1e-12)
        offset = 1000.0 * x + 5e5, 1000.0 * y + 5e5  # far from zero: the moments are taken about a pixel
        assert colour_ssim(*offset, data_range=255e3) == pytest.approx(skimage_ssim(*offset, data_range=255e3), abs=1e-12)


def test_kernel_batch_of_one_and_batches_bit_for_bit(rng):
    x = rng.integers(0, 256, (5, 70, 23, 3), dtype=np.uint8)
    y = noisy(rng, x, 25)
    batch = colour_ssim(x, y)
    np.testing.assert_allclose(batch, [skimage_ssim(x[i], y[i]) for i in range(5)], rtol=0, atol=1e-12)
    for i in range(5):
        assert colour_ssim(x[i:i + 1], y[i:i + 1]).shape == (1,)
        assert colour_ssim(x[i:i + 1], y[i:i + 1])[0] == batch[i] == colour_ssim(x[i], y[i])
    np.testing.assert_array_equal(colour_ssim(y, x), batch)


def test_kernel_non_contiguous_input(rng):
    base = rng.integers(0, 256, (2, 41, 60, 4), dtype=np.uint8)
    other = noisy(rng, base, 20)
    views = {
        "channel slice": (base[..., 1:], other[..., 1:]),
        "reversed channels and rows": (base[:, ::-1, :, 2::-1], other[:, ::-1, :, 2::-1]),
        "transposed": (base[..., :3].transpose(0, 2, 1, 3), other[..., :3].transpose(0, 2, 1, 3)),
        "strided": (base[:, ::2, 1::3, :3], other[:, ::2, 1::3, :3]),
        "one channel": (base[..., 3:], other[..., 3:]),
    }
    for name, (x, y) in views.items():
        assert not x.flags.c_contiguous, name
        expected = [skimage_ssim(x[i], y[i]) for i in range(2)]
        np.testing.assert_allclose(colour_ssim(x, y), expected, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_array_equal(colour_ssim(x, y), colour_ssim(x.copy(), y.copy()))
    # a permuted tensor, as score.py passes (N, C, H, W) images
    planar = torch.from_numpy(base[..., :3].transpose(0, 3, 1, 2).copy())
    other_planar = torch.from_numpy(other[..., :3].transpose(0, 3, 1, 2).copy())
    np.testing.assert_array_equal(colour_ssim(planar.permute(0, 2, 3, 1), other_planar.permute(0, 2, 3, 1)),
                                  colour_ssim(base[..., :3], other[..., :3]))


def test_kernel_float_dtypes_and_data_range(rng):
    x = rng.random((3, 30, 26, 3))
    y = np.clip(x + rng.normal(0, 0.05, x.shape), 0, 1)
    expected = [skimage_ssim(x[i], y[i], data_range=1.0) for i in range(3)]
    np.testing.assert_allclose(colour_ssim(x, y, data_range=1.0), expected, rtol=0, atol=1e-12)
    # data_range enters C1 and C2 only: the same images with L = 2 score differently, as skimage does
    np.testing.assert_allclose(colour_ssim(x, y, data_range=2.0), [skimage_ssim(x[i], y[i], data_range=2.0)
                                                                   for i in range(3)], rtol=0, atol=1e-12)
    assert not np.allclose(colour_ssim(x, y, data_range=2.0), expected)
    x8 = (255 * x).round().astype(np.uint8)
    y8 = (255 * y).round().astype(np.uint8)
    uint8_scores = colour_ssim(x8, y8)
    for cast in (np.float64, np.float32, np.int16):
        np.testing.assert_allclose(colour_ssim(x8.astype(cast), y8.astype(cast), data_range=255), uint8_scores,
                                   rtol=0, atol=1e-13)
    np.testing.assert_allclose(colour_ssim(x8, y8.astype(np.float64), data_range=255), uint8_scores, rtol=0, atol=1e-13)
    np.testing.assert_allclose(colour_ssim(torch.from_numpy(x8).float(), torch.from_numpy(y8).half(), data_range=255),
                               uint8_scores, rtol=0, atol=1e-13)


def test_kernel_pairwise_is_colour_ssim_of_each_pair(rng):
    a = rng.integers(0, 256, (3, 77, 18, 3), dtype=np.uint8)
    b = np.concatenate([noisy(rng, a, 25), rng.integers(0, 256, (1, 77, 18, 3), dtype=np.uint8), a[:1]])
    expected = np.array([[skimage_ssim(a[i], b[j]) for j in range(5)] for i in range(3)])
    loop = np.array([[colour_ssim(a[i], b[j]) for j in range(5)] for i in range(3)])
    for batch_size in (1, 4, 7, 256):
        matrix = pairwise_colour_ssim(a, b, batch_size=batch_size)
        np.testing.assert_allclose(matrix, expected, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(matrix, loop)
    assert pairwise_colour_ssim(a, b)[0, 4] == 1.0
    np.testing.assert_array_equal(pairwise_colour_ssim(b, a), loop.T)


def test_grey_ssim_runs_in_the_kernel_and_matches_skimage(rng):
    x = rng.integers(0, 256, (2, 33, 47, 3), dtype=np.uint8)
    y = noisy(rng, x, 20)
    for i in range(2):
        expected = structural_similarity(x[i] @ LUMA, y[i] @ LUMA, gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, data_range=255)
        assert grey_ssim(x, y)[i] == pytest.approx(expected, abs=1e-12)


def test_every_ssim_runs_in_the_kernel(monkeypatch, rng):
    kernel, calls = metrics._ssim_band_sums, []
    shared = metrics._ssim_band_sums_shared
    monkeypatch.setattr(metrics, "_ssim_band_sums", lambda x, *rest: calls.append(x.dtype) or kernel(x, *rest))
    monkeypatch.setattr(metrics, "_ssim_band_sums_shared",
                        lambda x, *rest: calls.append(("shared", x.dtype)) or shared(x, *rest))
    x = rng.integers(0, 256, (2, 20, 20, 3), dtype=np.uint8)
    colour_ssim(x, x)
    colour_ssim(x / 255.0, x / 255.0, data_range=1.0)
    grey_ssim(x, x)
    pairwise_colour_ssim(x, x)
    colour_ssim(torch.from_numpy(x), torch.from_numpy(x))
    assert calls == [np.uint8, np.float64, np.float64, ("shared", np.uint8), np.uint8]


def test_set_to_set_kernel_equals_the_paired_kernel_bit_for_bit(rng, monkeypatch):
    """The set-to-set path (each image's filtered mean computed once) gives the bits of the paired kernel
    on every pair: uint8 and float64, one and three channels, two row bands with a partial row block,
    blocks of the filtered means smaller than the sets, a set against itself."""
    monkeypatch.setattr(metrics, "FILTERED_BYTES", 3 * 8 * 3 * 67 * 13)  # blocks of 3 images
    for shape in ((7, 77, 23, 3), (5, 30, 41, 1)):
        a = rng.integers(0, 256, shape, dtype=np.uint8)
        b = np.concatenate([noisy(rng, a[:3], 30), rng.integers(0, 256, (2, *shape[1:]), dtype=np.uint8), a[:1]])
        for x, y, data_range in ((a, b, 255.0), (a / 7.0, b / 7.0, 255 / 7.0)):
            first, second = np.repeat(np.arange(len(x)), len(y)), np.tile(np.arange(len(y)), len(x))
            paired = metrics._kernel_ssim(*metrics._kernel_arrays(x[first], y[second]), np.arange(len(first)),
                                          np.arange(len(first)), data_range).reshape(len(x), len(y))
            for batch_size in (1, 5, 256):
                np.testing.assert_array_equal(pairwise_colour_ssim(x, y, data_range, batch_size), paired)
        np.testing.assert_array_equal(np.diag(pairwise_colour_ssim(a, a)), 1.0)
    # greyscale images (three equal channels) beside colour ones: a grey pair is computed on one channel
    grey = np.repeat(rng.integers(0, 256, (4, 40, 29, 1), dtype=np.uint8), 3, axis=3)
    mixed = np.concatenate([grey[:2], noisy(rng, grey[2:], 20)])
    first, second = np.repeat(np.arange(4), 4), np.tile(np.arange(4), 4)
    paired = metrics._kernel_ssim(*metrics._kernel_arrays(grey[first], mixed[second]), np.arange(16), np.arange(16),
                                  255.0).reshape(4, 4)
    np.testing.assert_array_equal(pairwise_colour_ssim(grey, mixed), paired)


def test_kernel_compiles_without_a_writable_cache():
    namespace: dict = {}
    exec("def double(v):\n    return 2 * v\n", namespace)  # no source file: numba has nowhere to cache it
    assert metrics._jit()(namespace["double"])(21) == 42


def test_bootstrap_interval_matches_the_normal_approximation_and_resamples_whole_groups():
    from vtgen.core.metrics import bootstrap_interval

    rng = np.random.default_rng(3)
    values = rng.normal(0.5, 0.1, 400)
    low, high = bootstrap_interval(values, resamples=4000, seed=0)
    half = 1.96 * values.std(ddof=1) / np.sqrt(len(values))
    assert low == pytest.approx(values.mean() - half, abs=0.002) and high == pytest.approx(values.mean() + half, abs=0.002)
    assert (low, high) == bootstrap_interval(values, resamples=4000, seed=0)  # seeded
    # 40 groups of 10 identical values: the images of a group are not independent, so the interval
    # is that of 40 values, about sqrt(10) times wider than if each image counted
    grouped = np.repeat(values[:40], 10)
    g_low, g_high = bootstrap_interval(grouped, np.repeat(np.arange(40), 10), resamples=4000)
    i_low, i_high = bootstrap_interval(grouped, resamples=4000)
    assert 2.5 < (g_high - g_low) / (i_high - i_low) < 4.0
    assert bootstrap_interval(np.array([0.2, 0.4]), np.array(["a", "a"])) == (pytest.approx(0.3), pytest.approx(0.3))
    assert bootstrap_interval(np.array([0.2, np.nan, 0.4]))[0] >= 0.2
    assert all(np.isnan(bootstrap_interval(np.array([np.nan]))))


def test_colour_ssim_leaves_torchs_thread_count_as_it_was():
    # numba's OpenMP layer sets the process's OpenMP thread count; a training job at 1 thread went on at 2
    # after its first validation SSIM, which changed its rounding (a resumed run then differed in the last bits)
    import torch

    from vtgen.core.metrics import colour_ssim

    before = torch.get_num_threads()
    images = np.random.default_rng(0).integers(0, 256, (4, 32, 32, 3), dtype=np.uint8)
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            colour_ssim(images, images[::-1].copy(), 255.0)
            assert torch.get_num_threads() == threads
    finally:
        torch.set_num_threads(before)
