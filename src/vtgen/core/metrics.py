"""Image-similarity metrics: SSIM per channel (Colour-SSIM), luma SSIM, set-to-set SSIM, PSNR.

Every function takes two images of the same shape, channels last: one image ``(H, W, C)`` or a
batch ``(N, H, W, C)``, as numpy arrays or torch tensors (converted to numpy on the CPU), of an
integer or real floating dtype. It returns float64 numpy scores: shape ``(N,)`` for a batch, a
0-d array for a single image (``float(s)`` or ``s.item()`` gives the number).
``pairwise_colour_ssim`` returns the ``(N, M)`` matrix.

``data_range`` (the ``L`` of the formulas, the distance between the darkest and the brightest
possible value) defaults to 255 for ``uint8`` images and must be given for any other dtype, as
in scikit-image: a float image in [0, 1] and one in [0, 255] cannot be told apart.

SSIM follows Wang et al. (2004) as scikit-image computes it with ``gaussian_weights=True,
sigma=1.5, use_sample_covariance=False``: local statistics under an 11-tap Gaussian window
(sigma 1.5, radius 5, weights normalised to sum 1), population covariance, and the mean of the
SSIM map over the pixels where the window lies inside the image, which makes the filtering a
separable "valid" convolution with no padding. Scores agree with scikit-image to 1e-12 in the tests (1.2e-15 measured, benchmarks/README.md).
Images smaller than the window (11 px) are refused.

There is one SSIM implementation: a fused float64 numba kernel (``_ssim_band_sums``) on the
CPU, compiled on first use and cached on disk where a cache directory is writable; Colour-SSIM
and grey SSIM (the SSIM of the luma image) run in it. Set-to-set SSIM runs in its twin for
recurring images (``_ssim_band_sums_shared``: each image's filtered mean computed once, the same
arithmetic in the same order, so the same bits, tested). numba's thread
setting is left alone, and torch's thread count is restored after each call (numba's OpenMP
layer changes it). There is no multi-scale SSIM (MS-SSIM): it needs images of at least 161 px
(the window at the fifth scale), larger than the pipeline's tiles.

References: Z. Wang, A. C. Bovik, H. R. Sheikh, E. P. Simoncelli, "Image quality assessment:
from error visibility to structural similarity", IEEE TIP 13 (2004). J.-T. Lee, D. Bollegala,
S. Luo, "'Touching to see' and 'seeing to feel'", ICRA 2019 (Colour-SSIM).
"""

from __future__ import annotations

import math
import sys

import numba
import numpy as np

__all__ = ["colour_ssim", "grey_ssim", "psnr", "pairwise_colour_ssim"]

K1, K2 = 0.01, 0.03
SIGMA = 1.5
RADIUS = 5  # int(3.5 * SIGMA + 0.5): scikit-image's truncate=3.5 with sigma 1.5
WINDOW = 2 * RADIUS + 1
LUMA_WEIGHTS = (0.299, 0.587, 0.114)  # ITU-R BT.601


def _gaussian_taps() -> list[float]:
    """The 1-D window: exp(-x^2 / (2 sigma^2)) for x = -5..5, divided by its sum (as scipy.ndimage)."""
    x = np.arange(-RADIUS, RADIUS + 1, dtype=np.float64)
    weights = np.exp(-0.5 / (SIGMA * SIGMA) * x**2)
    return (weights / weights.sum()).tolist()


TAPS = _gaussian_taps()


# ---------------------------------------------------------------------------------------------
# input checks


def _as_batch(image, name: str, channels: tuple[int, ...]) -> tuple[np.ndarray, tuple[int, ...]]:
    """``image`` as an (N, H, W, C) numpy array, and its shape as given (3-D for a single image).
    A torch tensor is detached and copied to the CPU (floating ones as float64, which is exact);
    torch itself is not imported here."""
    if hasattr(image, "detach"):
        image = image.detach().cpu()
        image = (image.double() if image.is_floating_point() else image).numpy()
    array = np.asarray(image)
    shape = array.shape
    if array.ndim not in (3, 4):
        raise ValueError(f"{name} has shape {shape}: expected one image (H, W, C) "
                         f"or a batch (N, H, W, C), channels last")
    if shape[-1] not in channels:
        raise ValueError(f"{name} has shape {shape}: expected C = "
                         f"{' or '.join(map(str, channels))} channels in the last axis")
    if array.dtype.kind not in "uif":
        raise ValueError(f"{name} has dtype {array.dtype}: expected uint8 or a real floating dtype")
    if array.dtype.kind == "f":
        if np.isnan(array).any():
            raise ValueError(f"{name} contains NaN values")
        if np.isinf(array).any():
            raise ValueError(f"{name} contains infinite values")
    return (array[None] if array.ndim == 3 else array), shape


def _resolve_data_range(a: np.ndarray, b: np.ndarray, data_range: float | None) -> float:
    """L: the caller's ``data_range``, or 255 when both images are uint8."""
    if data_range is None:
        if a.dtype == b.dtype == np.uint8:
            return 255.0
        raise ValueError(f"images of dtype {a.dtype}/{b.dtype} need an explicit data_range (the distance "
                         f"between the smallest and largest possible value, e.g. 1.0 for floats in [0, 1]); "
                         f"only uint8 images default to 255")
    data_range = float(data_range)
    if not (math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range must be a finite positive number, got {data_range}")
    return data_range


def _check_pair(a, b, channels: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, bool]:
    """Both images as (N, H, W, C) arrays, and whether they were single images."""
    x, a_shape = _as_batch(a, "a", channels)
    y, b_shape = _as_batch(b, "b", channels)
    if a_shape != b_shape:
        raise ValueError(f"a and b must have the same shape, got {a_shape} and {b_shape}")
    return x, y, len(a_shape) == 3


def _check_window(height: int, width: int) -> None:
    if height < WINDOW or width < WINDOW:
        raise ValueError(f"image is {height}x{width}, smaller than the 11x11 Gaussian window of SSIM")


# ---------------------------------------------------------------------------------------------
# the fused float64 kernel (numba): Colour-SSIM, grey SSIM and set-to-set SSIM on CPU

BAND_ROWS = 64  # output rows per kernel task; a task is (pair, channel, band of rows)
ROW_BLOCK = 4  # output rows filtered vertically at once, sharing their loads
G0, G1, G2, G3, G4, G5 = TAPS[:RADIUS + 1]  # the window is symmetric: TAPS[10 - u] == TAPS[u]


def _jit(**options):
    """``numba.njit`` caching the machine code on disk (numba's ``__pycache__`` next to this file,
    else its user-wide cache, or ``NUMBA_CACHE_DIR``); where none is writable numba refuses
    ``cache=True``, and the kernel is compiled again in each process instead."""
    def decorate(function):
        try:
            return numba.njit(cache=True, **options)(function)
        except RuntimeError:
            return numba.njit(**options)(function)
    return decorate


@_jit()
def _taps(v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10):
    """sum_u TAPS[u] v_u, adding the symmetric taps first (as scipy's correlate1d does)."""
    return G5 * v5 + G4 * (v4 + v6) + G3 * (v3 + v7) + G2 * (v2 + v8) + G1 * (v1 + v9) + G0 * (v0 + v10)


@_jit()
def _row_taps(rows, k, m, j):
    """Output j of the horizontal 11-tap filter of rows[k, m]: reads columns j .. j + 10."""
    return _taps(rows[k, m, j], rows[k, m, j + 1], rows[k, m, j + 2], rows[k, m, j + 3], rows[k, m, j + 4],
                 rows[k, m, j + 5], rows[k, m, j + 6], rows[k, m, j + 7], rows[k, m, j + 8], rows[k, m, j + 9],
                 rows[k, m, j + 10])


@_jit(inline="always")  # in the kernels' IR: a call per pixel would cost 3x
def _vertical_block(moments, m, o, j, vertical):
    """Outputs o .. o + 3 of the vertical 11-tap filter of moments[m] at column j, into vertical[0 .. 3, m, j]
    (input rows o .. o + 13, each read once)."""
    v0 = moments[m, o, j]
    v1 = moments[m, o + 1, j]
    v2 = moments[m, o + 2, j]
    v3 = moments[m, o + 3, j]
    v4 = moments[m, o + 4, j]
    v5 = moments[m, o + 5, j]
    v6 = moments[m, o + 6, j]
    v7 = moments[m, o + 7, j]
    v8 = moments[m, o + 8, j]
    v9 = moments[m, o + 9, j]
    v10 = moments[m, o + 10, j]
    v11 = moments[m, o + 11, j]
    v12 = moments[m, o + 12, j]
    v13 = moments[m, o + 13, j]
    vertical[0, m, j] = _taps(v0, v1, v2, v3, v4, v5, v6, v7, v8, v9, v10)
    vertical[1, m, j] = _taps(v1, v2, v3, v4, v5, v6, v7, v8, v9, v10, v11)
    vertical[2, m, j] = _taps(v2, v3, v4, v5, v6, v7, v8, v9, v10, v11, v12)
    vertical[3, m, j] = _taps(v3, v4, v5, v6, v7, v8, v9, v10, v11, v12, v13)


@_jit(inline="always")
def _ssim_term(mean_x, mean_y, second_sum, cross, x_o, y_o, c1, c2):
    """One pixel of the SSIM map from the filtered moments of the centred channels x' = x - x_o, y' = y - y_o:
    E[x'], E[y'], E[x'^2 + y'^2], E[x'y'] (Wang et al. 2004, eq. 13; the variances and covariance are
    unchanged by centring, the means are shifted back)."""
    mu_x = mean_x + x_o
    mu_y = mean_y + y_o
    luminance_num = mu_x * mu_y * 2.0 + c1
    luminance_den = mu_x * mu_x + mu_y * mu_y + c1
    contrast_num = (cross - mean_x * mean_y) * 2.0 + c2
    contrast_den = (second_sum - (mean_x * mean_x + mean_y * mean_y)) + c2
    return (luminance_num * contrast_num) / (luminance_den * contrast_den)


@_jit()
def _channel_means(images):
    """Mean of each channel of C-contiguous (N, H, W, C) images: float64 (N, C). Sums each
    position of the flattened rows over the rows first: contiguous, independent sums vectorise."""
    n, height, width, channels = images.shape
    flat = images.reshape((n, height, width * channels))
    means = np.empty((n, channels))
    for i in range(n):
        sums = np.zeros(width * channels)
        for r in range(height):
            for q in range(width * channels):
                sums[q] += flat[i, r, q]
        for c in range(channels):
            total = 0.0
            for q in range(c, width * channels, channels):
                total += sums[q]
            means[i, c] = total / (height * width)
    return means


@_jit(parallel=True)
def _ssim_band_sums(x, y, first, second, x_offsets, y_offsets, c1, c2):
    """Sums of the SSIM map (Wang et al. 2004) of the pairs (x[first[p]], y[second[p]]): float64
    (P, C, bands), per channel and band of ``BAND_ROWS`` output rows (the last band may be shorter).

    x (N, H, W, C) and y (M, H, W, C): C-contiguous arrays of one dtype (uint8 or float64), H and
    W >= 11; x_offsets (N, C) and y_offsets (M, C): ``_channel_means`` of x and y. Each task
    (pair, channel, band) streams its rows: the moments x', y', x'^2 + y'^2 and x'y' of the
    centred images x' = x - x_o, y' = y - y_o (SSIM's variances do not change under a shift, and
    centred moments lose less to cancellation in E[x'^2] - E[x']^2), the vertical 11-tap pass
    ``ROW_BLOCK`` rows at a time, then per output row the horizontal pass and the SSIM map

        ((2 mu_x mu_y + C1)(2 (E[x'y'] - E[x']E[y']) + C2))
        / ((mu_x^2 + mu_y^2 + C1)((E[x'^2 + y'^2] - (E[x']^2 + E[y']^2)) + C2)),  mu = E[x'] + x_o,

    summed per column over the band's rows, then over the columns. Plain float64 arithmetic, no
    fused multiply-add: swapping x and y gives the same bits, and x == y gives exactly 1. Scratch
    memory is allocated inside the task, where LLVM can tell it aliases nothing (needed to
    vectorise the loops): about 4 (BAND_ROWS + 13) W + 17 W doubles per task.
    """
    _, height, width, channels = x.shape
    out_h, out_w = height - 2 * RADIUS, width - 2 * RADIUS
    bands = (out_h + BAND_ROWS - 1) // BAND_ROWS
    sums = np.empty((first.shape[0], channels, bands))
    for task in numba.prange(first.shape[0] * channels * bands):
        p, c, band = task // (channels * bands), (task // bands) % channels, task % bands
        i, k = first[p], second[p]
        top = band * BAND_ROWS
        rows = min(BAND_ROWS, out_h - top)
        # moments of input rows top + r, r < rows + 10, then ROW_BLOCK - 1 rows of zeros read by
        # the last block when it is partial (its extra outputs are not used)
        moments = np.empty((4, rows + 2 * RADIUS + ROW_BLOCK - 1, width))
        moments[:, rows + 2 * RADIUS:] = 0.0
        vertical = np.empty((ROW_BLOCK, 4, width))
        column_sums = np.zeros(out_w)
        x_o = x_offsets[i, c]
        y_o = y_offsets[k, c]
        filled = 0
        for o in range(0, rows, ROW_BLOCK):
            for r in range(filled, min(o + ROW_BLOCK + 2 * RADIUS, rows + 2 * RADIUS)):
                for j in range(width):
                    a = np.float64(x[i, top + r, j, c]) - x_o
                    b = np.float64(y[k, top + r, j, c]) - y_o
                    moments[0, r, j] = a
                    moments[1, r, j] = b
                    moments[2, r, j] = a * a + b * b
                    moments[3, r, j] = a * b
                filled = r + 1
            for m in range(4):  # vertical pass: output rows o .. o + 3 from input rows o .. o + 13
                for j in range(width):
                    _vertical_block(moments, m, o, j, vertical)
            for row in range(min(ROW_BLOCK, rows - o)):  # horizontal pass and the SSIM map
                for j in range(out_w):
                    mean_x = _row_taps(vertical, row, 0, j)
                    mean_y = _row_taps(vertical, row, 1, j)
                    second_sum = _row_taps(vertical, row, 2, j)
                    cross = _row_taps(vertical, row, 3, j)
                    column_sums[j] += _ssim_term(mean_x, mean_y, second_sum, cross, x_o, y_o, c1, c2)
        total = 0.0
        for j in range(out_w):
            total += column_sums[j]
        sums[p, c, band] = total
    return sums


@_jit(parallel=True)
def _filtered_means(planar, offsets):
    """E[x'] of ``_ssim_band_sums`` for each image alone: float64 (N, C, H - 10, W - 10), the 11 x 11
    Gaussian-filtered centred channel x' = x - offsets[n, c] of planar (N, C, H, W) images, with the
    kernel's arithmetic (the same vertical, then horizontal taps), so each value equals the kernel's
    ``mean_x`` bit for bit."""
    n, channels, height, width = planar.shape
    out_h, out_w = height - 2 * RADIUS, width - 2 * RADIUS
    out = np.empty((n, channels, out_h, out_w))
    for task in numba.prange(n * channels):
        i, c = task // channels, task % channels
        offset = offsets[i, c]
        centred = np.empty((height, width))
        for r in range(height):
            for j in range(width):
                centred[r, j] = np.float64(planar[i, c, r, j]) - offset
        vertical = np.empty((1, 1, width))
        for r in range(out_h):
            for j in range(width):
                vertical[0, 0, j] = _taps(centred[r, j], centred[r + 1, j], centred[r + 2, j], centred[r + 3, j],
                                          centred[r + 4, j], centred[r + 5, j], centred[r + 6, j], centred[r + 7, j],
                                          centred[r + 8, j], centred[r + 9, j], centred[r + 10, j])
            for j in range(out_w):
                out[i, c, r, j] = _row_taps(vertical, 0, 0, j)
    return out


@_jit(parallel=True)
def _ssim_band_sums_shared(x, y, first, second, x_offsets, y_offsets, x_means, y_means, x_grey, y_grey, c1, c2):
    """``_ssim_band_sums`` for pairs whose images recur (a set-to-set matrix), equal to it bit for bit.

    x (N, C, H, W) and y (M, C, H, W): planar C-contiguous copies of the kernel's images (channels
    first, so a row of one channel is contiguous and its loads vectorise); x_offsets, y_offsets:
    their ``_channel_means``; x_means, y_means: their ``_filtered_means`` (each image's E[x'],
    computed once instead of once per pair). A task filters only the two moments that depend on the
    pair, x'^2 + y'^2 and x'y'; every operation that remains is the one of ``_ssim_band_sums``, in the
    same order (same bands, row blocks, taps and sums), so the sums are the same bits: 2x less time
    per pair (benchmarks/README.md, score stage, fourth round). x_grey, y_grey: images whose channels
    are all equal; for a pair of two such images only channel 0 is computed (the others would repeat
    its bits) and the entries of channels 1.. are left for the caller to copy from it."""
    _, channels, height, width = x.shape
    out_h, out_w = height - 2 * RADIUS, width - 2 * RADIUS
    bands = (out_h + BAND_ROWS - 1) // BAND_ROWS
    sums = np.empty((first.shape[0], channels, bands))
    for task in numba.prange(first.shape[0] * channels * bands):
        p, c, band = task // (channels * bands), (task // bands) % channels, task % bands
        i, k = first[p], second[p]
        if c > 0 and x_grey[i] and y_grey[k]:
            continue
        top = band * BAND_ROWS
        rows = min(BAND_ROWS, out_h - top)
        moments = np.empty((2, rows + 2 * RADIUS + ROW_BLOCK - 1, width))
        moments[:, rows + 2 * RADIUS:] = 0.0
        vertical = np.empty((ROW_BLOCK, 2, width))
        column_sums = np.zeros(out_w)
        x_o = x_offsets[i, c]
        y_o = y_offsets[k, c]
        filled = 0
        for o in range(0, rows, ROW_BLOCK):
            for r in range(filled, min(o + ROW_BLOCK + 2 * RADIUS, rows + 2 * RADIUS)):
                for j in range(width):
                    a = np.float64(x[i, c, top + r, j]) - x_o
                    b = np.float64(y[k, c, top + r, j]) - y_o
                    moments[0, r, j] = a * a + b * b
                    moments[1, r, j] = a * b
                filled = r + 1
            for m in range(2):
                for j in range(width):
                    _vertical_block(moments, m, o, j, vertical)
            for row in range(min(ROW_BLOCK, rows - o)):
                out_row = top + o + row
                for j in range(out_w):
                    mean_x = x_means[i, c, out_row, j]
                    mean_y = y_means[k, c, out_row, j]
                    second_sum = _row_taps(vertical, row, 0, j)
                    cross = _row_taps(vertical, row, 1, j)
                    column_sums[j] += _ssim_term(mean_x, mean_y, second_sum, cross, x_o, y_o, c1, c2)
        total = 0.0
        for j in range(out_w):
            total += column_sums[j]
        sums[p, c, band] = total
    return sums


def _kernel_arrays(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W, C) arrays as C-contiguous native arrays of one dtype the kernel is compiled
    for: uint8 when both are, else float64 (exact for every other input dtype)."""
    dtype = np.uint8 if x.dtype == y.dtype == np.uint8 else np.float64
    return np.ascontiguousarray(x, dtype=dtype), np.ascontiguousarray(y, dtype=dtype)


def _keep_torch_threads(kernel, *args):
    """``kernel(*args)``, with torch's thread count as it was before: numba's OpenMP threading layer sets
    the process-wide OpenMP thread count, which torch's CPU kernels share (a training job set to 1
    thread ran on 2 after its first validation SSIM, with other rounding)."""
    torch = sys.modules.get("torch")
    threads = torch.get_num_threads() if torch is not None else None
    result = kernel(*args)
    if threads is not None and torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return result


def _kernel_ssim(x: np.ndarray, y: np.ndarray, first: np.ndarray, second: np.ndarray, data_range: float,
                 x_means: np.ndarray | None = None, y_means: np.ndarray | None = None) -> np.ndarray:
    """Colour-SSIM (P,) of the pairs (x[first[p]], y[second[p]]): per channel, the mean of the SSIM
    map over its (H - 10)(W - 10) valid positions; then the mean over the channels. ``x_means``,
    ``y_means``: ``_channel_means`` of x and y, computed here if not given."""
    if len(first) == 0:
        return np.empty(0)
    x_means = _channel_means(x) if x_means is None else x_means
    y_means = _channel_means(y) if y_means is None else y_means
    sums = _keep_torch_threads(_ssim_band_sums, x, y, first.astype(np.int64), second.astype(np.int64), x_means,
                               y_means, (K1 * data_range) ** 2, (K2 * data_range) ** 2)
    return _scores_from_sums(sums, x.shape[1], x.shape[2])


def _scores_from_sums(sums: np.ndarray, height: int, width: int) -> np.ndarray:
    """(P,) SSIM from the kernels' (P, C, bands) sums of the map: mean over positions, then over channels."""
    positions = (height - 2 * RADIUS) * (width - 2 * RADIUS)
    return (sums.sum(axis=2) / positions).mean(axis=1)


FILTERED_BYTES = 1 << 27  # filtered means held at once per set by _pairwise_ssim (128 MiB: 1,900 tiles of 64 px)


def _pairwise_ssim(xs: np.ndarray, ys: np.ndarray, data_range: float, batch_size: int) -> np.ndarray:
    """(N, M) Colour-SSIM of every pair of kernel arrays xs (N, H, W, C) and ys (M, H, W, C), through
    ``_ssim_band_sums_shared``: each image's channel means and filtered means computed once (per block
    of at most ``FILTERED_BYTES`` of them), then ``batch_size`` pairs per kernel call, row by row.
    A pair of greyscale images (three equal channels, e.g. tactile frames) is computed on one channel."""
    n, height, width, channels = xs.shape
    m = ys.shape[0]
    matrix = np.empty((n, m))
    if n * m == 0:
        return matrix
    constants = ((K1 * data_range) ** 2, (K2 * data_range) ** 2)
    per_image = 8 * channels * (height - 2 * RADIUS) * (width - 2 * RADIUS)
    block = max(1, FILTERED_BYTES // per_image)

    def prepared(images):
        planar = np.ascontiguousarray(images.transpose(0, 3, 1, 2))
        offsets = _channel_means(np.ascontiguousarray(images))
        grey = (planar[:, 1:] == planar[:, :1]).all(axis=(1, 2, 3)) if channels > 1 else np.zeros(len(planar), bool)
        return planar, offsets, _keep_torch_threads(_filtered_means, planar, offsets), grey

    for y_start in range(0, m, block):
        y_planar, y_offsets, y_filtered, y_grey = prepared(ys[y_start:y_start + block])
        width_m = len(y_planar)
        for x_start in range(0, n, block):
            x_planar, x_offsets, x_filtered, x_grey = prepared(xs[x_start:x_start + block])
            count = len(x_planar) * width_m
            scores = np.empty(count)
            for start in range(0, count, int(batch_size)):
                pairs = np.arange(start, min(start + int(batch_size), count))
                first, second = pairs // width_m, pairs % width_m
                sums = _keep_torch_threads(_ssim_band_sums_shared, x_planar, y_planar, first, second, x_offsets,
                                           y_offsets, x_filtered, y_filtered, x_grey, y_grey, *constants)
                grey = x_grey[first] & y_grey[second]  # channels equal in both images: channel 0's bits
                sums[grey, 1:] = sums[grey, :1]
                scores[pairs] = _scores_from_sums(sums, height, width)
            matrix[x_start:x_start + len(x_planar), y_start:y_start + width_m] = scores.reshape(len(x_planar), width_m)
    return matrix


def _paired_ssim(x: np.ndarray, y: np.ndarray, data_range: float) -> np.ndarray:
    """SSIM (n,) of the pairs (x[i], y[i]) of (n, H, W, C) arrays, averaged over the channels."""
    _check_window(x.shape[1], x.shape[2])
    pairs = np.arange(x.shape[0])
    return _kernel_ssim(*_kernel_arrays(x, y), pairs, pairs, data_range)


# ---------------------------------------------------------------------------------------------
# public metrics


def colour_ssim(a, b, data_range: float | None = None) -> np.ndarray:
    """Colour-SSIM: SSIM (Wang et al. 2004) of each channel, averaged over the channels.

    SSIM(x, y) = mean over the valid window positions of
    ((2 mu_x mu_y + C1)(2 sigma_xy + C2)) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)),
    C1 = (0.01 L)^2, C2 = (0.03 L)^2, L = ``data_range``, local statistics under the 11x11
    Gaussian window (sigma 1.5), population covariance. Equals scikit-image's
    ``structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=L)`` (to 1e-12), computed in float64.

    Parameters
    ----------
    a, b : array or tensor, (H, W, C) or (N, H, W, C), C = 1 or 3, same shape
    data_range : L; default 255 for uint8 input, required otherwise

    Returns
    -------
    float64 array (N,) for a batch, 0-d for one image, each in [-1, 1].

    Raises
    ------
    ValueError : shapes differ, ndim not 3 or 4, C not 1 or 3, NaN or infinite values, float input
        without ``data_range``, or an image side under 11 px (the window).

    Notes
    -----
    Identical images score exactly 1.0. Zero-variance (constant) images are finite: the contrast
    term is C2 / C2 = 1, so constants c1 and c2 score (2 c1 c2 + C1) / (c1^2 + c2^2 + C1); two
    equal constants score 1; all-black vs all-white uint8 scores C1 / (255^2 + C1) = 6.5025 /
    65031.5025 ~ 9.999e-5. Variances are not clamped, as in scikit-image: the denominator
    sigma_x^2 + sigma_y^2 + C2 stays >= C2 > 0 up to rounding of order 1e-16 L^2.
    """
    x, y, single = _check_pair(a, b, (1, 3))
    scores = _paired_ssim(x, y, _resolve_data_range(x, y, data_range))
    return scores[0] if single else scores


def grey_ssim(a, b, data_range: float | None = None) -> np.ndarray:
    """SSIM of the luma images Y = 0.299 R + 0.587 G + 0.114 B (ITU-R BT.601).

    Inputs are RGB (C = 3), shapes and ``data_range`` as in :func:`colour_ssim` (luma keeps the
    range of the channels, so L is unchanged); the luma is computed in float64 and scored by the
    same kernel, as one channel. Returns float64 (N,) or 0-d; raises as :func:`colour_ssim`.
    """
    x, y, single = _check_pair(a, b, (3,))
    data_range = _resolve_data_range(x, y, data_range)
    luma = lambda images: (images @ np.array(LUMA_WEIGHTS))[..., None]
    scores = _paired_ssim(luma(x), luma(y), data_range)
    return scores[0] if single else scores


def psnr(a, b, data_range: float | None = None) -> np.ndarray:
    """Peak signal-to-noise ratio 10 log10(L^2 / MSE), MSE over all pixels and channels of each image.

    Same shapes and ``data_range`` rules as :func:`colour_ssim` (C = 1 or 3); equals
    ``skimage.metrics.peak_signal_noise_ratio(a, b, data_range=L)``. Returns float64 dB, (N,) or
    0-d; identical images (MSE = 0) give ``np.inf``.
    """
    x, y, single = _check_pair(a, b, (1, 3))
    data_range = _resolve_data_range(x, y, data_range)
    mse = np.square(x.astype(np.float64) - y.astype(np.float64)).mean(axis=(1, 2, 3))
    with np.errstate(divide="ignore"):
        scores = 10 * np.log10(data_range**2 / mse)
    return scores[0] if single else scores


def pairwise_colour_ssim(a, b, data_range: float | None = None, batch_size: int = 256) -> np.ndarray:
    """(N, M) matrix of :func:`colour_ssim` between every a[i] and every b[j] (set-to-set SSIM).

    Each image's channel means and filtered means are computed once and every pair filters only the
    two moments it owns (``_ssim_band_sums_shared``), with the arithmetic of :func:`colour_ssim`'s
    kernel in the same order, so entries equal ``colour_ssim(a[i], b[j])`` bit for bit; exactly 1
    where a[i] == b[j]. Scratch: float64 filtered means of up to 2 x 128 MiB at once.

    Parameters
    ----------
    a : (N, H, W, C) or one (H, W, C) image (then N = 1); b : (M, H, W, C) or one image
        (M = 1); same H, W and C (1 or 3), same dtype rules and ``data_range`` as colour_ssim
    batch_size : pairs per call of the kernel (its scratch memory is per task, not per pair)

    Returns
    -------
    float64 array (N, M).
    """
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    x, a_shape = _as_batch(a, "a", (1, 3))
    y, b_shape = _as_batch(b, "b", (1, 3))
    if x.shape[1:] != y.shape[1:]:
        raise ValueError(f"a and b must hold images of the same (H, W, C), got {a_shape} and {b_shape}")
    data_range = _resolve_data_range(x, y, data_range)
    _check_window(*x.shape[1:3])
    return _pairwise_ssim(*_kernel_arrays(x, y), data_range, batch_size)


def bootstrap_interval(values: np.ndarray, groups: np.ndarray | None = None, resamples: int = 1000,
                       seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Percentile bootstrap interval (Efron & Tibshirani 1993) of the mean of ``values``, resampling whole
    ``groups`` (e.g. the test sources, whose images are not independent) with replacement; every value is
    its own group when ``groups`` is None. NaN values are ignored. (nan, nan) when no finite value is
    left; (m, m) for a single group, whose spread cannot be estimated from the data."""
    values = np.asarray(values, dtype=np.float64)
    groups = np.arange(len(values)) if groups is None else np.asarray(groups)
    keep = np.isfinite(values)
    values, groups = values[keep], groups[keep]
    if len(values) == 0:
        return math.nan, math.nan
    labels, index = np.unique(groups, return_inverse=True)
    sums = np.bincount(index, weights=values, minlength=len(labels))
    counts = np.bincount(index, minlength=len(labels)).astype(np.float64)
    if len(labels) == 1:
        mean = float(sums[0] / counts[0])
        return mean, mean
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(labels), size=(resamples, len(labels)))
    means = sums[draws].sum(axis=1) / counts[draws].sum(axis=1)
    tail = (1 - level) / 2
    low, high = np.quantile(means, [tail, 1 - tail])
    return float(low), float(high)
