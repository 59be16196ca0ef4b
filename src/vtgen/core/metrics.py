"""Image-similarity metrics: SSIM per channel (Colour-SSIM), luma SSIM, PSNR, MS-SSIM.

Every function takes two images of the same shape, channels last: one image ``(H, W, C)`` or a
batch ``(N, H, W, C)``, as numpy arrays or torch tensors, ``uint8`` or floating. It returns
float64 numpy scores: shape ``(N,)`` for a batch, a 0-d array for a single image (``float(s)``
or ``s.item()`` gives the number). ``pairwise_colour_ssim`` returns the ``(N, M)`` matrix.

``data_range`` (the ``L`` of the formulas, the distance between the darkest and the brightest
possible value) defaults to 255 for ``uint8`` images and must be given for any other dtype, as
in scikit-image: a float image in [0, 1] and one in [0, 255] cannot be told apart.

SSIM follows Wang et al. (2004) as scikit-image computes it with ``gaussian_weights=True,
sigma=1.5, use_sample_covariance=False``: local statistics under an 11-tap Gaussian window
(sigma 1.5, radius 5, weights normalised to sum 1), population covariance, and the mean of the
SSIM map over the pixels where the window lies inside the image, which makes the filtering a
separable "valid" convolution with no padding. Scores agree with scikit-image to about 1e-13
on float64 input (``dtype=torch.float64``, the default). Images smaller than the window (11 px)
are refused, and MS-SSIM needs ``ms_ssim_min_size()`` px.

Colour-SSIM, grey SSIM and set-to-set SSIM in float64 on CPU (the default) run in one fused
numba kernel (``_ssim_band_sums``), compiled on first use and cached on disk where a cache
directory is writable. Everything else (``dtype=torch.float32``, tensors on a GPU, MS-SSIM)
runs in torch on the device of ``a`` (CPU for numpy input), in chunks of images small enough to
stay near the CPU cache. torch's and numba's thread settings are left alone.

References: Z. Wang, A. C. Bovik, H. R. Sheikh, E. P. Simoncelli, "Image quality assessment:
from error visibility to structural similarity", IEEE TIP 13 (2004). Z. Wang, E. P. Simoncelli,
A. C. Bovik, "Multiscale structural similarity for image quality assessment", Asilomar 2003.
J.-T. Lee, D. Bollegala, S. Luo, "'Touching to see' and 'seeing to feel'", ICRA 2019 (Colour-SSIM).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["colour_ssim", "grey_ssim", "psnr", "ms_ssim", "ms_ssim_min_size", "pairwise_colour_ssim"]

K1, K2 = 0.01, 0.03
SIGMA = 1.5
RADIUS = 5  # int(3.5 * SIGMA + 0.5): scikit-image's truncate=3.5 with sigma 1.5
WINDOW = 2 * RADIUS + 1
LUMA_WEIGHTS = (0.299, 0.587, 0.114)  # ITU-R BT.601
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)  # Wang, Simoncelli & Bovik (2003)
CHUNK_ELEMENTS = 1 << 19  # elements of the maps filtered at once (4 MiB in float64), near the caches


def _gaussian_taps() -> list[float]:
    """The 1-D window: exp(-x^2 / (2 sigma^2)) for x = -5..5, divided by its sum (as scipy.ndimage)."""
    x = np.arange(-RADIUS, RADIUS + 1, dtype=np.float64)
    weights = np.exp(-0.5 / (SIGMA * SIGMA) * x**2)
    return (weights / weights.sum()).tolist()


TAPS = _gaussian_taps()


# ---------------------------------------------------------------------------------------------
# input checks


def _as_tensor(image, name: str) -> torch.Tensor:
    if isinstance(image, torch.Tensor):
        return image.detach()
    array = np.asarray(image)
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    return torch.from_numpy(np.ascontiguousarray(array))


def _as_batch(image, name: str, channels: tuple[int, ...]) -> tuple[torch.Tensor, tuple[int, ...]]:
    """``image`` as an (N, H, W, C) tensor, and its shape as given (3-D for a single image)."""
    tensor = _as_tensor(image, name)
    shape = tuple(tensor.shape)
    if tensor.ndim not in (3, 4):
        raise ValueError(f"{name} has shape {shape}: expected one image (H, W, C) "
                         f"or a batch (N, H, W, C), channels last")
    if shape[-1] not in channels:
        raise ValueError(f"{name} has shape {shape}: expected C = "
                         f"{' or '.join(map(str, channels))} channels in the last axis")
    if tensor.dtype == torch.bool or tensor.is_complex():
        raise ValueError(f"{name} has dtype {tensor.dtype}: expected uint8 or a real floating dtype")
    if tensor.is_floating_point():
        if torch.isnan(tensor).any():
            raise ValueError(f"{name} contains NaN values")
        if torch.isinf(tensor).any():
            raise ValueError(f"{name} contains infinite values")
    return (tensor.unsqueeze(0) if tensor.ndim == 3 else tensor), shape


def _resolve_data_range(a: torch.Tensor, b: torch.Tensor, data_range: float | None) -> float:
    """L: the caller's ``data_range``, or 255 when both images are uint8."""
    if data_range is None:
        if a.dtype == torch.uint8 and b.dtype == torch.uint8:
            return 255.0
        raise ValueError(f"images of dtype {a.dtype}/{b.dtype} need an explicit data_range (the distance "
                         f"between the smallest and largest possible value, e.g. 1.0 for floats in [0, 1]); "
                         f"only uint8 images default to 255")
    data_range = float(data_range)
    if not (math.isfinite(data_range) and data_range > 0):
        raise ValueError(f"data_range must be a finite positive number, got {data_range}")
    return data_range


def _check_pair(a, b, channels: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """Both images as (N, H, W, C) tensors on a's device, and whether they were single images."""
    x, a_shape = _as_batch(a, "a", channels)
    y, b_shape = _as_batch(b, "b", channels)
    if a_shape != b_shape:
        raise ValueError(f"a and b must have the same shape, got {a_shape} and {b_shape}")
    return x, y.to(x.device), len(a_shape) == 3


def _check_window(height: int, width: int, minimum: int = WINDOW,
                  what: str = "the 11x11 Gaussian window of SSIM") -> None:
    if height < minimum or width < minimum:
        raise ValueError(f"image is {height}x{width}, smaller than {what}")


def _result(scores: torch.Tensor | np.ndarray, single: bool) -> np.ndarray:
    out = scores if isinstance(scores, np.ndarray) else scores.detach().to("cpu", torch.float64).numpy()
    return out[0] if single else out


def _chunks(n: int, per_item: int, limit: int | None = None):
    """Slices of range(n) holding about CHUNK_ELEMENTS / per_item items each (at most ``limit``)."""
    size = max(1, CHUNK_ELEMENTS // max(per_item, 1))
    if limit is not None:
        size = max(1, min(size, limit))
    for start in range(0, n, size):
        yield slice(start, min(start + size, n))


def _check_dtype(dtype: torch.dtype) -> None:
    if dtype not in (torch.float64, torch.float32):
        raise ValueError(f"dtype must be torch.float64 or torch.float32, got {dtype}")


# ---------------------------------------------------------------------------------------------
# filtering and the SSIM formula


class _Workspace:
    """Scratch buffers reused by the chunks of one call, by name: a fresh multi-megabyte tensor
    per operation costs page faults that take as long as the arithmetic."""

    def __init__(self, device: torch.device):
        self.device = device
        self._flat: dict[str, torch.Tensor] = {}

    def take(self, name: str, shape: tuple[int, ...], dtype: torch.dtype = torch.float64) -> torch.Tensor:
        size = math.prod(shape)
        flat = self._flat.get(name)
        if flat is None or flat.dtype != dtype or flat.numel() < size:
            flat = self._flat[name] = torch.empty(size, dtype=dtype, device=self.device)
        return flat[:size].view(shape)


# The float64 filter adds the taps from the centre outwards as a running weighted average,
# one ``lerp`` per tap: after tap j the buffer holds sum_{i<=j} g_i x_i / sum_{i<=j} g_i, and
# after the last, the weights summing to 1, the filtered value. Ten passes over memory instead
# of eleven (a scaling and ten multiply-adds): 17% faster in float64; in float32 lerp is slower.
CENTRE_OUT = sorted(range(WINDOW), key=lambda i: (abs(i - RADIUS), i))
LERP_WEIGHTS = [TAPS[i] / sum(TAPS[j] for j in CENTRE_OUT[:k + 1]) for k, i in enumerate(CENTRE_OUT)]


def _filter_axis(shifted, out: torch.Tensor) -> torch.Tensor:
    """out = sum_s TAPS[s] * shifted(s) for s = 0..10, where shifted(s) is the input moved by s."""
    if out.dtype == torch.float64:
        torch.lerp(shifted(CENTRE_OUT[0]), shifted(CENTRE_OUT[1]), LERP_WEIGHTS[1], out=out)
        for shift, weight in zip(CENTRE_OUT[2:], LERP_WEIGHTS[2:]):
            out.lerp_(shifted(shift), weight)
    else:
        torch.mul(shifted(RADIUS), TAPS[RADIUS], out=out)
        for shift, tap in enumerate(TAPS):
            if shift != RADIUS:
                out.add_(shifted(shift), alpha=tap)
    return out


def _gaussian_valid(maps: torch.Tensor, workspace: _Workspace) -> torch.Tensor:
    """Separable 11-tap Gaussian "valid" filtering of (n, K, H, W) maps -> (n, K, H - 10, W - 10).

    Output pixel (i, j) is sum_{u,v} g_u g_v maps[..., i + u, j + v] with g = ``TAPS``: what
    scipy's ``gaussian_filter(sigma=1.5, truncate=3.5)`` gives at (i + 5, j + 5), a value that
    only reads the image interior. Each axis is a sum of shifted slices, in the dtype of
    ``maps``; the result is a float64 workspace buffer (use it before the next call).

    Design notes: on CPU this is memory bound (each pass reads two maps and writes one), so
    callers filter chunks of about ``CHUNK_ELEMENTS``, near the cache sizes. torch's float64
    conv2d is several times slower than these slices; oneDNN's float32 depthwise convolution is
    faster in isolation but needs channels-last copies and fresh output tensors, whose page
    faults cost about what it saves.
    """
    n, k, height, width = maps.shape
    out_h, out_w = height - 2 * RADIUS, width - 2 * RADIUS
    maps = maps.contiguous()
    vertical = _filter_axis(lambda s: maps[:, :, s:s + out_h],
                            workspace.take("vertical", (n, k, out_h, width), maps.dtype))
    filtered = _filter_axis(lambda s: vertical[..., s:s + out_w],
                            workspace.take("filtered", (n, k, out_h, out_w), maps.dtype))
    if filtered.dtype == torch.float64:
        return filtered
    return workspace.take("filtered float64", filtered.shape).copy_(filtered)


def _planar(images: torch.Tensor, dtype: torch.dtype, workspace: _Workspace, name: str) -> torch.Tensor:
    """(n, H, W, C) images of any dtype -> contiguous (n, C, H, W) workspace buffer in ``dtype``.
    Done once per chunk, transposing before converting: the other order and strided
    single-channel views cost several times more."""
    n, height, width, channels = images.shape
    planar = workspace.take(name, (n, channels, height, width), dtype)
    if images.dtype == dtype:
        return planar.copy_(images.permute(0, 3, 1, 2))
    transposed = workspace.take(name + " transposed", (n, channels, height, width), images.dtype)
    return planar.copy_(transposed.copy_(images.permute(0, 3, 1, 2)))


def _centre_into(planar: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """Write x - c of (n, C, H, W) images into ``out`` (same dtype), c being each channel's mean
    rounded to that dtype; return c as (n, C, 1, 1) float64.

    SSIM's (co)variances do not change under a shift, and centred values keep E[x^2] - mu^2
    from cancelling catastrophically (which matters in float32; in float64 it is harmless). In
    float32, x - c is exact for uint8 x (both are multiples of 2^-16 below 256), and c is the
    value actually subtracted, so mu = E[x'] + c stays consistent.
    """
    offsets = planar.mean(dim=(2, 3), keepdim=True)  # any consistent shift works; this one is small
    torch.sub(planar, offsets, out=out)
    return offsets.to(torch.float64)


def _ssim_terms(mean_x, mean_y, offset_x, offset_y, second_sum, cross, data_range: float, workspace: _Workspace,
                want_cs: bool = False):
    """Per-channel means of the SSIM map and (if ``want_cs``, else None) of its contrast-structure
    map: (n, C) tensors.

    Inputs are float64 Gaussian-filtered statistics of centred images x' = x - c_x,
    y' = y - c_y: mean_x = E[x'], mean_y = E[y'] (may broadcast), second_sum = E[x'^2] + E[y'^2]
    and cross = E[x'y'], both (n, C, h, w) and overwritten. With mu = E[x'] + c,
    sigma_x^2 + sigma_y^2 = second_sum - E[x']^2 - E[y']^2, sigma_xy = cross - E[x']E[y'],
    C1 = (K1 L)^2, C2 = (K2 L)^2:

        cs   = (2 sigma_xy + C2) / (sigma_x^2 + sigma_y^2 + C2)
        SSIM = (2 mu_x mu_y + C1) / (mu_x^2 + mu_y^2 + C1) * cs

    For x == y both maps come out exactly 1: numerator and denominator agree bit for bit (only
    plain products and sums, no fused multiply-add, whose single rounding would break the tie).
    """
    c1 = (K1 * data_range) ** 2
    c2 = (K2 * data_range) ** 2
    shape = cross.shape
    mean_x, mean_y = mean_x.expand(shape), mean_y.expand(shape)
    mu_x = torch.add(mean_x, offset_x, out=workspace.take("mu_x", shape))
    mu_y = torch.add(mean_y, offset_y, out=workspace.take("mu_y", shape))
    luminance_num = torch.mul(mu_x, mu_y, out=workspace.take("luminance_num", shape)).mul_(2).add_(c1)
    luminance_den = torch.mul(mu_x, mu_x, out=workspace.take("luminance_den", shape))
    luminance_den.add_(torch.mul(mu_y, mu_y, out=mu_x)).add_(c1)
    contrast_num = cross.sub_(torch.mul(mean_x, mean_y, out=mu_x)).mul_(2).add_(c2)
    squares = torch.mul(mean_x, mean_x, out=mu_x).add_(torch.mul(mean_y, mean_y, out=mu_y))
    contrast_den = second_sum.sub_(squares).add_(c2)
    ssim = luminance_num.mul_(contrast_num).div_(luminance_den.mul_(contrast_den)).mean(dim=(-2, -1))
    return ssim, (contrast_num.div_(contrast_den).mean(dim=(-2, -1)) if want_cs else None)


def _ssim_per_channel(x: torch.Tensor, y: torch.Tensor, data_range: float, dtype: torch.dtype,
                      workspace: _Workspace, want_cs: bool = False):
    """SSIM and cs (None unless ``want_cs``), each (n, C), of (n, C, H, W) image pairs in
    ``dtype`` (one chunk): filters the maps x', y', x'^2 + y'^2 and x'y' of the centred images."""
    n, channels, height, width = x.shape
    maps = workspace.take("maps", (n, 4 * channels, height, width), dtype)
    xc, yc, squares, cross = maps.split(channels, dim=1)
    offset_x = _centre_into(x, xc)
    offset_y = _centre_into(y, yc)
    torch.mul(xc, xc, out=squares).add_(torch.mul(yc, yc, out=cross))
    torch.mul(xc, yc, out=cross)
    mean_x, mean_y, second_sum, cross = _gaussian_valid(maps, workspace).split(channels, dim=1)
    return _ssim_terms(mean_x, mean_y, offset_x, offset_y, second_sum, cross, data_range, workspace, want_cs)


def _chunked_per_channel(x: torch.Tensor, y: torch.Tensor, dtype: torch.dtype, score) -> torch.Tensor:
    """(n, C) float64 tensor of ``score(x_part, y_part, workspace)`` over chunks of images; the
    parts are planar (n', C, H, W) in ``dtype``."""
    n, height, width, channels = x.shape
    workspace = _Workspace(x.device)
    per_channel = torch.empty((n, channels), dtype=torch.float64, device=x.device)
    for part in _chunks(n, 4 * channels * height * width):
        x_planar, y_planar = _planar(x[part], dtype, workspace, "x"), _planar(y[part], dtype, workspace, "y")
        per_channel[part] = score(x_planar, y_planar, workspace)
    return per_channel


def _colour_ssim_batch(x: torch.Tensor, y: torch.Tensor, data_range: float, dtype: torch.dtype,
                      use_kernel: bool = True) -> np.ndarray:
    """Colour-SSIM (n,) float64 of (n, H, W, C) pairs: the numba kernel where ``_use_kernel``
    (unless ``use_kernel`` is False), else torch."""
    _check_window(x.shape[1], x.shape[2])
    if use_kernel and _use_kernel(x, dtype):
        pairs = np.arange(x.shape[0])
        return _kernel_ssim(*_kernel_arrays(x, y), pairs, pairs, data_range)
    score = lambda xs, ys, workspace: _ssim_per_channel(xs, ys, data_range, dtype, workspace)[0]
    return _result(_chunked_per_channel(x, y, dtype, score).mean(dim=1), False)


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
            for row in range(min(ROW_BLOCK, rows - o)):  # horizontal pass and the SSIM map
                for j in range(out_w):
                    mean_x = _row_taps(vertical, row, 0, j)
                    mean_y = _row_taps(vertical, row, 1, j)
                    second_sum = _row_taps(vertical, row, 2, j)
                    cross = _row_taps(vertical, row, 3, j)
                    mu_x = mean_x + x_o
                    mu_y = mean_y + y_o
                    luminance_num = mu_x * mu_y * 2.0 + c1
                    luminance_den = mu_x * mu_x + mu_y * mu_y + c1
                    contrast_num = (cross - mean_x * mean_y) * 2.0 + c2
                    contrast_den = (second_sum - (mean_x * mean_x + mean_y * mean_y)) + c2
                    column_sums[j] += (luminance_num * contrast_num) / (luminance_den * contrast_den)
        total = 0.0
        for j in range(out_w):
            total += column_sums[j]
        sums[p, c, band] = total
    return sums


def _use_kernel(x: torch.Tensor, dtype: torch.dtype) -> bool:
    """Whether SSIM of these images runs in the numba kernel: float64 computation on CPU."""
    return dtype == torch.float64 and x.device.type == "cpu"


def _kernel_arrays(x: torch.Tensor, y: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(n, H, W, C) CPU tensors as C-contiguous numpy arrays of one dtype the kernel is compiled
    for: uint8 when both are, else float64 (exact for every other input dtype)."""
    dtype = torch.uint8 if x.dtype == y.dtype == torch.uint8 else torch.float64
    return tuple(np.ascontiguousarray(t.to(dtype).numpy()) for t in (x, y))


def _kernel_ssim(x: np.ndarray, y: np.ndarray, first: np.ndarray, second: np.ndarray, data_range: float,
                 x_means: np.ndarray | None = None, y_means: np.ndarray | None = None) -> np.ndarray:
    """Colour-SSIM (P,) of the pairs (x[first[p]], y[second[p]]): per channel, the mean of the SSIM
    map over its (H - 10)(W - 10) valid positions; then the mean over the channels. ``x_means``,
    ``y_means``: ``_channel_means`` of x and y, computed here if not given."""
    if len(first) == 0:
        return np.empty(0)
    x_means = _channel_means(x) if x_means is None else x_means
    y_means = _channel_means(y) if y_means is None else y_means
    sums = _ssim_band_sums(x, y, first.astype(np.int64), second.astype(np.int64), x_means, y_means,
                           (K1 * data_range) ** 2, (K2 * data_range) ** 2)
    positions = (x.shape[1] - 2 * RADIUS) * (x.shape[2] - 2 * RADIUS)
    return (sums.sum(axis=2) / positions).mean(axis=1)


# ---------------------------------------------------------------------------------------------
# public metrics


def colour_ssim(a, b, data_range: float | None = None, *, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """Colour-SSIM: SSIM (Wang et al. 2004) of each channel, averaged over the channels.

    SSIM(x, y) = mean over the valid window positions of
    ((2 mu_x mu_y + C1)(2 sigma_xy + C2)) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)),
    C1 = (0.01 L)^2, C2 = (0.03 L)^2, L = ``data_range``, local statistics under the 11x11
    Gaussian window (sigma 1.5), population covariance. Equals scikit-image's
    ``structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False, data_range=L)`` (to ~1e-13 on float64 input).

    Parameters
    ----------
    a, b : array or tensor, (H, W, C) or (N, H, W, C), C = 1 or 3, same shape
    data_range : L; default 255 for uint8 input, required otherwise
    dtype : torch.float64 (default; exact to rounding; on CPU the fused numba kernel) or
        torch.float32 (torch: the filtering runs in float32 on mean-centred images, the formula
        in float64; differs from float64 by ~1e-7 on natural images, up to a few 1e-6 on
        high-contrast ones; on CPU slower than the float64 kernel, meant for GPU tensors)

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
    return _colour_ssim(a, b, data_range, dtype, use_kernel=True)


def _colour_ssim(a, b, data_range: float | None, dtype: torch.dtype, use_kernel: bool) -> np.ndarray:
    _check_dtype(dtype)
    x, y, single = _check_pair(a, b, (1, 3))
    data_range = _resolve_data_range(x, y, data_range)
    return _result(_colour_ssim_batch(x, y, data_range, dtype, use_kernel), single)


def _torch_colour_ssim(a, b, data_range: float | None = None, *, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """:func:`colour_ssim` computed in torch whatever the device (the path before the numba
    kernel, kept for the GPU and float32; benchmarks and tests compare against it)."""
    return _colour_ssim(a, b, data_range, dtype, use_kernel=False)


def grey_ssim(a, b, data_range: float | None = None, *, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """SSIM of the luma images Y = 0.299 R + 0.587 G + 0.114 B (ITU-R BT.601).

    Inputs are RGB (C = 3), shapes and ``data_range`` as in :func:`colour_ssim` (luma keeps the
    range of the channels, so L is unchanged); the luma is computed in float64 and scored by the
    same single-channel SSIM. Returns float64 (N,) or 0-d; raises as :func:`colour_ssim`.
    """
    _check_dtype(dtype)
    x, y, single = _check_pair(a, b, (3,))
    data_range = _resolve_data_range(x, y, data_range)
    _check_window(x.shape[1], x.shape[2])
    weights = torch.tensor(LUMA_WEIGHTS, dtype=torch.float64, device=x.device)
    luma = lambda images: (images.to(torch.float64) * weights).sum(dim=-1, keepdim=True)
    scores = [_colour_ssim_batch(luma(x[part]), luma(y[part]), data_range, dtype)
              for part in _chunks(x.shape[0], x[0].numel())]
    return _result(np.concatenate(scores) if scores else np.empty(0), single)


def psnr(a, b, data_range: float | None = None) -> np.ndarray:
    """Peak signal-to-noise ratio 10 log10(L^2 / MSE), MSE over all pixels and channels of each image.

    Same shapes and ``data_range`` rules as :func:`colour_ssim` (C = 1 or 3); equals
    ``skimage.metrics.peak_signal_noise_ratio(a, b, data_range=L)``. Returns float64 dB, (N,) or
    0-d; identical images (MSE = 0) give ``np.inf``.
    """
    x, y, single = _check_pair(a, b, (1, 3))
    data_range = _resolve_data_range(x, y, data_range)
    mse = np.empty(x.shape[0], dtype=np.float64)
    per_image = x[0].numel() if x.shape[0] else 1
    for part in _chunks(x.shape[0], per_image):
        difference = x[part].to(torch.float64) - y[part].to(torch.float64)
        mse[part] = difference.square_().mean(dim=(1, 2, 3)).cpu().numpy()
    with np.errstate(divide="ignore"):
        scores = 10 * np.log10(data_range**2 / mse)
    return scores[0] if single else scores


def ms_ssim_min_size() -> int:
    """Smallest image side :func:`ms_ssim` accepts: 161 px.

    Each of the four 2x2 downsamplings maps a side s to ceil(s / 2), and the fifth (coarsest)
    scale must still hold the 11 px window: ceil(s / 16) >= 11, i.e. s >= (11 - 1) * 2^4 + 1.
    """
    side = WINDOW
    for _ in MS_SSIM_WEIGHTS[1:]:
        side = 2 * side - 1
    return side


def _halve(images: torch.Tensor) -> torch.Tensor:
    """2x2 average pooling of (n, C, H, W) images to ceil(H/2) x ceil(W/2); an odd last row or
    column is averaged over the pixels that exist."""
    return F.avg_pool2d(images, kernel_size=2, stride=2, ceil_mode=True)


def ms_ssim(a, b, data_range: float | None = None, *, dtype: torch.dtype = torch.float64) -> np.ndarray:
    """Multi-scale SSIM (Wang, Simoncelli & Bovik 2003), per channel and averaged over channels.

    MS-SSIM = prod_{j=1..4} max(cs_j, 0)^{w_j} * max(SSIM_5, 0)^{w_5}, w = (0.0448, 0.2856,
    0.3001, 0.2363, 0.1333), where cs_j is the mean contrast-structure map
    (2 sigma_xy + C2) / (sigma_x^2 + sigma_y^2 + C2) at scale j, SSIM_5 the SSIM of
    :func:`colour_ssim` at the coarsest scale, each with the same 11-tap Gaussian valid window,
    and scale j + 1 is scale j 2x2 average-pooled (see ``_halve``). Negative cs or SSIM (anti-
    correlated structure) is clamped at 0 before the power, as pytorch-msssim does, so the score
    lies in [0, 1].

    Shapes, C = 1 or 3, ``data_range`` and ``dtype`` as in :func:`colour_ssim`; both sides must
    be at least ``ms_ssim_min_size()`` (161) px, else ValueError. Identical images score exactly 1.
    Returns float64 (N,) or 0-d.
    """
    _check_dtype(dtype)
    x, y, single = _check_pair(a, b, (1, 3))
    data_range = _resolve_data_range(x, y, data_range)
    n, height, width, channels = x.shape
    minimum = ms_ssim_min_size()
    _check_window(height, width, minimum, f"the {minimum}x{minimum} minimum of MS-SSIM (ms_ssim_min_size())")
    weights = torch.tensor(MS_SSIM_WEIGHTS, dtype=torch.float64, device=x.device)

    def score(xs: torch.Tensor, ys: torch.Tensor, workspace: _Workspace) -> torch.Tensor:
        factors = []
        for scale in range(len(MS_SSIM_WEIGHTS)):
            ssim, cs = _ssim_per_channel(xs, ys, data_range, dtype, workspace, want_cs=True)
            if scale == len(MS_SSIM_WEIGHTS) - 1:
                factors.append(ssim)
            else:
                factors.append(cs)
                xs, ys = _halve(xs), _halve(ys)
        return torch.stack(factors).clamp_(min=0).pow_(weights.view(-1, 1, 1)).prod(dim=0)

    return _result(_chunked_per_channel(x, y, dtype, score).mean(dim=1), single)


def _image_statistics(images: torch.Tensor, data_range: float, dtype: torch.dtype, workspace: _Workspace,
                      keep: bool):
    """The per-image parts of SSIM for (n, H, W, C) images, computed once for every pair an image
    is in: the centred images x' (n, C, H, W) in ``dtype``, and float64 (n, C, H-10, W-10) maps
    E[x'], mu = E[x'] + c, mu^2 + C1/2 and sigma^2 + C2/2 (sigma^2 = E[x'^2] - E[x']^2). In new
    tensors if ``keep``, else in workspace buffers (valid until the next call)."""
    n, height, width, channels = images.shape
    maps = workspace.take("maps", (n, 2 * channels, height, width), dtype)
    centred, squares = maps.split(channels, dim=1)
    offsets = _centre_into(_planar(images, dtype, workspace, "x"), centred)
    torch.mul(centred, centred, out=squares)
    mean, second = _gaussian_valid(maps, workspace).split(channels, dim=1)
    shape = mean.shape

    def new(name: str, shape, dtype=torch.float64) -> torch.Tensor:
        if keep:
            return torch.empty(shape, dtype=dtype, device=images.device)
        return workspace.take("statistics " + name, shape, dtype)

    centred = new("centred", centred.shape, dtype).copy_(centred)
    mean = new("mean", shape).copy_(mean)
    mu = torch.add(mean, offsets, out=new("mu", shape))
    luminance_half = torch.mul(mu, mu, out=new("luminance", shape)).add_((K1 * data_range) ** 2 / 2)
    contrast_half = torch.mul(mean, mean, out=new("contrast", shape))
    contrast_half = torch.sub(second, contrast_half, out=contrast_half).add_((K2 * data_range) ** 2 / 2)
    return centred, mean, mu, luminance_half, contrast_half


def _pair_ssim(stats_x, stats_y, cross: torch.Tensor, data_range: float, workspace: _Workspace) -> torch.Tensor:
    """Per-channel SSIM (k, C) of image pairs from their per-image statistics (each may
    broadcast over the k pairs) and the filtered cross moment E[x'y'] (k, C, h, w, overwritten):

        SSIM = (2 mu_x mu_y + C1)(2 (E[x'y'] - E[x']E[y']) + C2)
               / (((mu_x^2 + C1/2) + (mu_y^2 + C1/2)) ((sigma_x^2 + C2/2) + (sigma_y^2 + C2/2)))

    For x == y numerator and denominator agree bit for bit, as in ``_ssim_terms``.
    """
    _, mean_x, mu_x, luminance_x, contrast_x = stats_x
    _, mean_y, mu_y, luminance_y, contrast_y = stats_y
    shape = cross.shape
    scratch = workspace.take("scratch", shape)
    contrast_num = cross.sub_(torch.mul(mean_x, mean_y, out=scratch)).mul_(2).add_((K2 * data_range) ** 2)
    luminance_num = torch.mul(mu_x, mu_y, out=workspace.take("luminance_num", shape)).mul_(2)
    luminance_num.add_((K1 * data_range) ** 2).mul_(contrast_num)
    denominator = torch.add(luminance_x, luminance_y, out=scratch)
    denominator.mul_(torch.add(contrast_x, contrast_y, out=workspace.take("contrast_den", shape)))
    return luminance_num.div_(denominator).mean(dim=(-2, -1))


def pairwise_colour_ssim(a, b, data_range: float | None = None, batch_size: int = 256, *,
                         dtype: torch.dtype = torch.float64) -> np.ndarray:
    """(N, M) matrix of :func:`colour_ssim` between every a[i] and every b[j] (set-to-set SSIM).

    float64 on CPU: every pair runs through the fused kernel of :func:`colour_ssim` (recomputing
    an image's statistics costs less than storing and reading them back), so entries equal
    ``colour_ssim(a[i], b[j])`` bit for bit. Otherwise (float32, GPU) torch computes each image's
    filtered mean E[x] and variance once and each pair adds only its filtered cross moment E[xy]
    and the formula; entries equal colour_ssim to ~1e-15. Exactly 1 where a[i] == b[j].

    Parameters
    ----------
    a : (N, H, W, C) or one (H, W, C) image (then N = 1); b : (M, H, W, C) or one image
        (M = 1); same H, W and C (1 or 3), same dtype rules and ``data_range`` as colour_ssim
    batch_size : at most this many pairs are computed together (in torch fewer for large
        images, to keep the working set near the cache); memory is bounded by it
    dtype : as in :func:`colour_ssim`

    Returns
    -------
    float64 array (N, M). In torch the statistics of the smaller set are held in memory: per
    image C * H * W values of ``dtype`` and 4 C (H-10)(W-10) float64 values (SSIM is symmetric;
    the larger set is streamed one image at a time).
    """
    return _pairwise_colour_ssim(a, b, data_range, batch_size, dtype, use_kernel=True)


def _torch_pairwise_colour_ssim(a, b, data_range: float | None = None, batch_size: int = 256, *,
                                dtype: torch.dtype = torch.float64) -> np.ndarray:
    """:func:`pairwise_colour_ssim` computed in torch whatever the device (see ``_torch_colour_ssim``)."""
    return _pairwise_colour_ssim(a, b, data_range, batch_size, dtype, use_kernel=False)


def _pairwise_colour_ssim(a, b, data_range: float | None, batch_size: int, dtype: torch.dtype,
                          use_kernel: bool) -> np.ndarray:
    _check_dtype(dtype)
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    x, a_shape = _as_batch(a, "a", (1, 3))
    y, b_shape = _as_batch(b, "b", (1, 3))
    if x.shape[1:] != y.shape[1:]:
        raise ValueError(f"a and b must hold images of the same (H, W, C), got {a_shape} and {b_shape}")
    y = y.to(x.device)
    data_range = _resolve_data_range(x, y, data_range)
    _check_window(*x.shape[1:3])
    if use_kernel and _use_kernel(x, dtype):
        return _kernel_pairwise(x, y, data_range, int(batch_size))
    if x.shape[0] < y.shape[0]:
        return _pairwise(y, x, data_range, int(batch_size), dtype).T.copy()
    return _pairwise(x, y, data_range, int(batch_size), dtype)


def _kernel_pairwise(x: torch.Tensor, y: torch.Tensor, data_range: float, batch_size: int) -> np.ndarray:
    """(N, M) Colour-SSIM of every pair, ``batch_size`` pairs per call of the numba kernel."""
    n, m = x.shape[0], y.shape[0]
    xs, ys = _kernel_arrays(x, y)
    x_means, y_means = _channel_means(xs), _channel_means(ys)
    matrix = np.empty(n * m)
    for start in range(0, n * m, batch_size):
        pairs = np.arange(start, min(start + batch_size, n * m))
        matrix[pairs] = _kernel_ssim(xs, ys, pairs // m, pairs % m, data_range, x_means, y_means)
    return matrix.reshape(n, m)


def _pairwise(streamed: torch.Tensor, held: torch.Tensor, data_range: float, batch_size: int,
              dtype: torch.dtype) -> np.ndarray:
    n, height, width, channels = streamed.shape
    m = held.shape[0]
    per_channel = torch.empty((n, m, channels), dtype=torch.float64, device=streamed.device)
    if n == 0 or m == 0:
        return per_channel.mean(dim=2).cpu().numpy()
    workspace = _Workspace(streamed.device)
    held_parts = [_image_statistics(held[part], data_range, dtype, workspace, keep=True)
                  for part in _chunks(m, 2 * channels * height * width)]
    held_stats = [torch.cat(parts) for parts in zip(*held_parts)]
    for i in range(n):
        stats = _image_statistics(streamed[i:i + 1], data_range, dtype, workspace, keep=False)
        for part in _chunks(m, 2 * channels * height * width, batch_size):
            part_stats = [t[part] for t in held_stats]
            products = workspace.take("maps", (part.stop - part.start, channels, height, width), dtype)
            cross = _gaussian_valid(torch.mul(stats[0], part_stats[0], out=products), workspace)
            per_channel[i, part] = _pair_ssim(stats, part_stats, cross, data_range, workspace)
    return per_channel.mean(dim=2).cpu().numpy()
