"""Distribution metrics for unaligned data: scores that rank real > generated > blur, offline.

Set-to-set Colour-SSIM rewards blur on unaligned data: a flat mean-colour image scores higher
against real images than real images do. The metrics here compare the *distributions* of two
image sets instead, and punish a set that lacks texture:

* features: :class:`RandomEncoder` (a fixed random-weight CNN, no downloaded weights) or the
  penultimate layer of vtgen's own classifier (:func:`classifier_encoder`), through
  :func:`image_features`;
* :func:`kid` (Bińkowski et al. 2018, with torchmetrics' subset draws) and
  :func:`fid` (Heusel et al. 2017, an exact form that stays accurate for singular covariances)
  on those features;
* :func:`spectrum_distance`: distance between azimuthally averaged log power spectra
  (Durall et al. 2020) of the greyscale images, no features;
* :func:`two_sample_test`: classifier two-sample test (Lopez-Paz & Oquab 2017), held-out accuracy
  with a Wilson interval;
* :func:`prdc_scores`: precision and recall (Kynkäänniemi et al. 2019), density and coverage
  (Naeem et al. 2020), as the authors' ``prdc`` package defines them;
* :func:`memorisation`: are generated images closer to the training images than held-out real
  images are?
* :func:`gaussian_blur`, :func:`flat_colour_set`, :func:`mean_image_set`: the trivial baselines.

Image inputs are uint8 tensors ``N x 3 x H x W`` (greyscale as three equal channels); feature
inputs are real ``N x D`` tensors (or arrays). Every function either returns the value its
docstring documents for degenerate input or raises ``ValueError`` saying what it needs.
The module is pure: no files, no parameters; sklearn (slow to import)
are imported inside the functions that use them.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from vtgen.core.classifier import AlexNet, scale_images, wilson_interval
from vtgen.core.spectrum import log_radial_profiles, LUMA, QUANTISATION_PSD

__all__ = [
    "RANDOM_ENCODER_SEED", "RANDOM_ENCODER_CHANNELS", "BLUR_FRACTION", "QUANTISATION_PSD",
    "RandomEncoder", "PenultimateFeatures", "classifier_encoder", "image_features",
    "kid", "fid", "fid_interval", "fid_and_interval", "radial_power_spectrum", "spectrum_distance", "log_spectra",
    "TwoSampleResult", "two_sample_test", "prdc_scores", "MemorisationResult", "memorisation",
    "memorisation_from_distances", "memorisation_from_nearest", "nearest_distances", "pairwise_distances",
    "pixel_squared_distances",
    "DiversityResult", "diversity_ratio", "grey_pixels",
    "median_interval",
    "gaussian_blur", "default_blur_sigma", "flat_colour_set", "mean_image_set",
]

RANDOM_ENCODER_SEED = 0
RANDOM_ENCODER_CHANNELS = (32, 64, 128, 128)
MIN_ENCODER_SIDE = 16
BLUR_FRACTION = 1 / 32  # default blur sigma = side / 32 (2 px at 64 px, 8 px at 256 px)
MIN_SPECTRUM_SIDE = 8


# --------------------------------------------------------------------------- input checks

def _check_images(images, name: str) -> torch.Tensor:
    if not isinstance(images, torch.Tensor) or images.dtype != torch.uint8 or images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"{name}: expected uint8 images N x 3 x H x W, got "
                         f"{getattr(images, 'dtype', type(images).__name__)} {tuple(getattr(images, 'shape', ()))}")
    return images


def _as_features(features, name: str, min_rows: int = 1, metric: str = "this metric") -> torch.Tensor:
    """Real ``N x D`` tensor or array -> float64 CPU tensor; refuses other shapes, NaN/inf and N < min_rows."""
    if isinstance(features, np.ndarray):
        features = torch.from_numpy(features)
    if not isinstance(features, torch.Tensor) or features.ndim != 2 or features.is_complex() or features.dtype == torch.bool:
        raise ValueError(f"{name}: expected real features N x D, got "
                         f"{getattr(features, 'dtype', type(features).__name__)} {tuple(getattr(features, 'shape', ()))}")
    if features.shape[1] == 0:
        raise ValueError(f"{name}: features have no dimensions (N x 0)")
    features = features.detach().to("cpu", torch.float64)
    # any NaN or infinity makes the sum non-finite, and a sum is several times cheaper than an element-wise
    # test, which then runs only to tell a real NaN or infinity from a sum that overflowed
    if not math.isfinite(float(features.sum())) and not torch.isfinite(features).all():
        raise ValueError(f"{name}: features contain NaN or infinite values")
    if len(features) < min_rows:
        raise ValueError(f"{metric} needs at least {min_rows} images per set, got {len(features)} in {name}")
    return features


def _pair(real, fake, min_rows: int, metric: str) -> tuple[torch.Tensor, torch.Tensor]:
    x = _as_features(real, "real", min_rows, metric)
    y = _as_features(fake, "fake", min_rows, metric)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"{metric}: real and fake features differ in dimension ({x.shape[1]} vs {y.shape[1]})")
    return x, y


# --------------------------------------------------------------------------- encoders

class RandomEncoder(nn.Module):
    """Fixed random-weight CNN that maps uint8 ``N x 3 x H x W`` tiles (H, W >= 16) to ``N x num_features`` texture statistics.

    Architecture: input scaled to [-1, 1] (x / 127.5 - 1, as the classifier does); four stages of
    3 x 3 convolution (reflect padding 1, no bias) + ReLU with ``channels`` = (32, 64, 128, 128)
    outputs, a 2 x 2 average pool between stages. After each stage the per-channel spatial mean
    and standard deviation (population) are taken, so the features see texture at receptive fields
    of 3, 8, 18 and 38 px, plus its contrast; ``num_features`` = 2 * sum(channels) = 704.
    Weights are He-normal (std sqrt(2 / fan_in)) drawn in float32 from a ``torch.Generator``
    seeded with ``seed`` (:data:`RANDOM_ENCODER_SEED`), in a fixed order, so they are the same bit
    for bit on every machine; they are buffers, not parameters (nothing to train). Random
    shallow networks are known to capture texture statistics (Ustyuzhaninov et al. 2017,
    "What does it take to generate natural textures?", ICLR).
    Float input is refused: pass the uint8 tiles.
    """

    def __init__(self, channels: tuple[int, ...] = RANDOM_ENCODER_CHANNELS, seed: int = RANDOM_ENCODER_SEED):
        super().__init__()
        if not channels or any(int(c) < 1 for c in channels):
            raise ValueError(f"channels must be positive integers, got {channels!r}")
        self.channels = tuple(int(c) for c in channels)
        self.seed = int(seed)
        generator = torch.Generator(device="cpu").manual_seed(self.seed)
        c_in = 3
        for i, c_out in enumerate(self.channels):
            weight = torch.randn(c_out, c_in, 3, 3, generator=generator, dtype=torch.float32)
            self.register_buffer(f"weight{i}", weight * math.sqrt(2.0 / (c_in * 9)))
            c_in = c_out
        self.num_features = 2 * sum(self.channels)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """uint8 N x 3 x H x W -> float32 N x num_features (means of every stage, then their stds)."""
        _check_images(images, "RandomEncoder input")
        if min(images.shape[-2:]) < MIN_ENCODER_SIDE:
            raise ValueError(f"RandomEncoder needs images of at least {MIN_ENCODER_SIDE} x {MIN_ENCODER_SIDE}, "
                             f"got {images.shape[-1]} x {images.shape[-2]}")
        x = images.to(self.weight0.device, torch.float32) / 127.5 - 1.0
        means, stds = [], []
        for i in range(len(self.channels)):
            if i:
                x = F.avg_pool2d(x, 2)
            x = F.relu(F.conv2d(F.pad(x, (1, 1, 1, 1), mode="reflect"), getattr(self, f"weight{i}")))
            var, mean = torch.var_mean(x, dim=(2, 3), correction=0)
            means.append(mean)
            stds.append(var.sqrt())
        return torch.cat(means + stds, dim=1)


class PenultimateFeatures(nn.Module):
    """vtgen's :class:`~vtgen.core.classifier.AlexNet` cut before its last layer: uint8 tiles -> fc7 activations (after ReLU).

    The tiles go through the classifier's own :func:`~vtgen.core.classifier.scale_images` ([-1, 1],
    channels-last), its conv stack, adaptive pool and fc6/fc7 (with dropout off in eval mode, which
    :func:`image_features` sets), exactly as in training. Tiles must have the side the model was
    trained on (``model.size``); ``num_features`` is fc7's width. The model is shared, not copied.
    """

    def __init__(self, model: AlexNet):
        super().__init__()
        if not isinstance(model, AlexNet):
            raise ValueError(f"PenultimateFeatures takes a vtgen AlexNet, got {type(model).__name__}")
        self.model = model
        self.num_features = int(model.classifier.fc7.out_features)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        _check_images(images, "classifier input")
        if tuple(images.shape[-2:]) != (self.model.size, self.model.size):
            raise ValueError(f"the classifier was trained on {self.model.size} x {self.model.size} tiles, "
                             f"got {images.shape[-1]} x {images.shape[-2]}")
        m = self.model
        x = torch.flatten(m.avgpool(m.features(scale_images(images))), 1)
        head = m.classifier
        x = head.relu6(head.fc6(head.drop6(x)))
        return head.relu7(head.fc7(head.drop7(x)))


def classifier_encoder(model: AlexNet) -> PenultimateFeatures:
    """The penultimate-layer (fc7) feature extractor of a trained vtgen classifier; see :class:`PenultimateFeatures`."""
    return PenultimateFeatures(model)


@torch.no_grad()
def image_features(encoder: nn.Module, images: torch.Tensor, batch_size: int = 64) -> torch.Tensor:
    """Features of uint8 ``N x 3 x H x W`` ``images`` by ``encoder`` in eval mode, without gradients: float64 ``N x D`` on the CPU.

    The encoder's train/eval mode is restored afterwards. An empty set gives ``0 x num_features``
    (``0 x 0`` if the encoder has no ``num_features``). Non-finite features are a ValueError.
    """
    _check_images(images, "images")
    if int(batch_size) < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    if len(images) == 0:
        return torch.empty(0, int(getattr(encoder, "num_features", 0)), dtype=torch.float64)
    parameters = list(encoder.parameters()) + list(encoder.buffers())
    device = parameters[0].device if parameters else torch.device("cpu")
    was_training = encoder.training
    encoder.eval()
    try:
        parts = [encoder(images[start:start + int(batch_size)].to(device)).to("cpu", torch.float64)
                 for start in range(0, len(images), int(batch_size))]
    finally:
        encoder.train(was_training)
    features = torch.cat(parts).reshape(len(images), -1)
    if not torch.isfinite(features).all():
        raise ValueError("the encoder returned NaN or infinite features")
    return features


# --------------------------------------------------------------------------- KID, FID

def _cube(values: np.ndarray) -> np.ndarray:
    """values ** 3 as two products (numpy's power calls pow() per element: 10x slower; within 2 ulp of it)."""
    return values * values * values


def kid(real, fake, subsets: int = 100, subset_size: int | None = None, seed: int = 0) -> tuple[float, float]:
    """Kernel Inception Distance of two feature sets: (mean, std) of the unbiased MMD^2 over random subsets.

    MMD^2_u = sum_{i != j} k(x_i, x_j) / (m (m - 1)) + sum_{i != j} k(y_i, y_j) / (m (m - 1))
    - 2 sum_{i, j} k(x_i, y_j) / m^2 with the cubic polynomial kernel k(x, y) = (x.y / D + 1)^3
    (Bińkowski et al. 2018, "Demystifying MMD GANs", ICLR), in float64. Each of ``subsets``
    draws takes ``subset_size`` rows of each set without replacement (default
    ``min(n_real, n_fake, 1000)``); the draws come from torch's generator seeded with ``seed``
    inside ``torch.random.fork_rng``, so the result is reproducible and the global RNG is left
    alone. ``std`` is the population std over subsets.

    The draws and the formula are those of torchmetrics' ``KernelInceptionDistance`` (tests agree
    with it to 1e-9), but the three kernel matrices are computed once and each subset indexes them:
    torchmetrics recomputes three float64 products per subset, which took 10.7 s of the score
    stage's 46 s on the default run (312 calls of 50 subsets), and importing it costs seconds.

    Values: about 0 for two samples of one distribution, positive otherwise; unbiased, so
    slightly negative values occur. A set against itself with ``subset_size`` = n gives exactly
    -2 / n (mean k(x_i, x_i) - mean_{i != j} k(x_i, x_j)) <= 0, std 0 (to rounding). Needs at least 2 rows per set
    and 2 <= subset_size <= min(n_real, n_fake) (ValueError otherwise).
    """
    x, y = _pair(real, fake, 2, "KID")
    if isinstance(subsets, bool) or not isinstance(subsets, int) or subsets < 1:
        raise ValueError(f"KID subsets must be an integer >= 1, got {subsets!r}")
    largest = min(len(x), len(y))
    size = min(largest, 1000) if subset_size is None else subset_size
    if isinstance(size, bool) or not isinstance(size, int) or not 2 <= size <= largest:
        raise ValueError(f"KID subset_size must be an integer in [2, {largest}] (the smaller set), got {size!r}")
    xs, ys = x.double().numpy(), y.double().numpy()
    dim = xs.shape[1]
    k_xx, k_yy, k_xy = (_cube(a @ b.T / dim + 1.0) for a, b in ((xs, xs), (ys, ys), (xs, ys)))
    scores = np.empty(subsets)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        for i in range(subsets):  # torchmetrics' draws, in its order: real rows, then fake rows
            r = torch.randperm(len(xs))[:size].numpy()
            f = torch.randperm(len(ys))[:size].numpy()
            sub_xx, sub_yy = k_xx[np.ix_(r, r)], k_yy[np.ix_(f, f)]
            within = (sub_xx.sum() - np.trace(sub_xx) + sub_yy.sum() - np.trace(sub_yy)) / (size * (size - 1))
            scores[i] = within - 2 * k_xy[np.ix_(r, f)].sum() / size ** 2
    return float(scores.mean()), float(scores.std())


def fid(real, fake) -> float:
    """Fréchet distance between Gaussians fitted to two feature sets (Heusel et al. 2017, NeurIPS).

    FID = |mu_r - mu_f|^2 + Tr(S_r) + Tr(S_f) - 2 Tr (S_r S_f)^(1/2), with sample covariances
    S = X^T X / (n - 1) of the centred features X, in float64. The cross term is computed
    exactly from the data: the non-zero eigenvalues of S_r S_f are the squared singular values of
    X_r X_f^T / sqrt((n_r - 1)(n_f - 1)), so Tr (S_r S_f)^(1/2) = ||X_r X_f^T||_* /
    sqrt((n_r - 1)(n_f - 1)) (nuclear norm), evaluated as the singular values of R_r R_f^T from
    thin QR factorisations X = Q R (a matrix of side at most min(n, D)).

    Not torchmetrics' ``FrechetInceptionDistance``, for a measured reason: it takes the square
    roots of the eigenvalues of S_r S_f, and for singular covariances (n <= D, the usual case
    here: 704 features from a few dozen tiles) rounding of the zero eigenvalues (about
    eps * |S|^2) becomes sqrt(eps) * |S| after the root. A set against itself then gave
    -2.7e-5 (n 15, D 704, features in [0, 1]) and -0.27 for the same features times 100; this
    form gives 0 to 1e-12. It agrees with torchmetrics and with scipy's ``sqrtm`` where those are
    accurate (n > D, tests).

    Values: 0 for identical sets (rounding below 0 is returned as 0), larger = further apart;
    finite for singular covariances, zero-variance features and constant sets (FID of two
    constant sets = |c_r - c_f|^2). The scale depends on the features: compare values from one
    encoder only. Needs at least 2 rows per set (ValueError).
    """
    x, y = _pair(real, fake, 2, "FID")
    mu_x, mu_y = x.mean(dim=0), y.mean(dim=0)
    xc, yc = x - mu_x, y - mu_y
    scale_x, scale_y = len(x) - 1, len(y) - 1
    r_x = torch.linalg.qr(xc, mode="r").R
    r_y = torch.linalg.qr(yc, mode="r").R
    cross = torch.linalg.svdvals(r_x @ r_y.T).sum() / math.sqrt(scale_x * scale_y)
    value = (mu_x - mu_y).square().sum() + xc.square().sum() / scale_x + yc.square().sum() / scale_y - 2 * cross
    return max(float(value), 0.0)


def _fid_from_grams(g_xx: np.ndarray, g_yy: np.ndarray, g_xy: np.ndarray, w_x: np.ndarray | None = None,
                    w_y: np.ndarray | None = None) -> float:
    """FID of two sets given their uncentred Gram matrices X X^T, Y Y^T and X Y^T (float64 numpy):
    |mu_x - mu_y|^2 from the Gram means, Tr S from the diagonals, and Tr (S_x S_y)^(1/2) as the nuclear
    norm of the doubly centred cross Gram (the form of :func:`fid`), so no D-sized matrix is formed.

    ``w_x``, ``w_y``: how many times each row occurs in the set (default once each), so a bootstrap
    draw is scored on its distinct rows. A row repeated w times is the same as a row scaled by
    sqrt(w) in the centred cross Gram (X = P X_d with P^T P = diag(w)), which leaves its singular
    values unchanged: the draw's FID at a third of the SVD's cost (a draw holds about 63% distinct rows)."""
    w_x = np.ones(len(g_xx)) if w_x is None else w_x
    w_y = np.ones(len(g_yy)) if w_y is None else w_y
    n, m = w_x.sum(), w_y.sum()
    p_x, p_y = w_x / n, w_y / m
    mean_xx, mean_yy = p_x @ g_xx @ p_x, p_y @ g_yy @ p_y
    row_means, column_means = g_xy @ p_y, p_x @ g_xy
    mean_xy = p_x @ row_means
    centred = g_xy - row_means[:, None] - column_means[None, :] + mean_xy
    scaled = np.sqrt(w_x)[:, None] * centred * np.sqrt(w_y)[None, :]
    cross = np.linalg.svd(scaled, compute_uv=False).sum() / math.sqrt((n - 1) * (m - 1))
    trace_x = (w_x @ np.diag(g_xx) - n * mean_xx) / (n - 1)
    trace_y = (w_y @ np.diag(g_yy) - m * mean_yy) / (m - 1)
    return max(float(mean_xx + mean_yy - 2 * mean_xy + trace_x + trace_y - 2 * cross), 0.0)


def _distinct_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(distinct rows, index of each row's distinct row, counts): a set that repeats vectors (the mean and
    flat baselines repeat one image per class) as its distinct vectors with their counts, which gives
    the same FID (the repeat argument of :func:`_fid_from_grams`) on far smaller matrices. Counts are
    None when every row is distinct, so such a set takes the unweighted path, unchanged."""
    ids: dict = {}
    firsts: list[int] = []  # the first row of each distinct vector
    of = np.empty(len(rows), dtype=np.int64)
    for row, key in enumerate(_row_keys(rows)):
        if key not in ids:
            ids[key] = len(firsts)
            firsts.append(row)
        of[row] = ids[key]
    if len(firsts) == len(rows):
        return rows, of, None
    return rows[firsts], of, np.bincount(of).astype(np.float64)


FID_PARALLEL_ROWS = 128  # distinct rows of both sets from which the bootstrap draws run in two threads
_BLAS: list = []  # the threadpoolctl controller of the BLAS numpy loaded, found on first use


def _one_blas_thread_each(function, items: list, parallel: bool) -> list:
    """``[function(item) for item in items]`` with numpy's BLAS on one thread, in ``torch.get_num_threads()``
    Python threads when ``parallel`` (LAPACK releases the GIL). For many small factorisations one
    thread each is the faster split on 2 cores, and under load it avoids OpenBLAS's threads waiting for
    each other (a 300 x 300 SVD took 7 ms on one thread, 44 ms on two beside another job)."""
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import ThreadpoolController  # a dependency of scikit-learn

    if not _BLAS:
        _BLAS.append(ThreadpoolController())
    workers = max(1, min(torch.get_num_threads(), len(items))) if parallel else 1
    with _BLAS[0].limit(limits=1, user_api="blas"):
        if workers == 1:
            return [function(item) for item in items]
        with ThreadPoolExecutor(workers) as pool:
            return list(pool.map(function, items))


def _check_fid_resamples(resamples) -> None:
    if isinstance(resamples, bool) or not isinstance(resamples, int) or resamples < 0 or resamples == 1:
        raise ValueError(f"FID resamples must be 0 or an integer >= 2, got {resamples!r}")


def _bias_corrected_interval(draws: np.ndarray, value: float, level: float) -> tuple[float, float]:
    """Percentile interval of bootstrap ``draws`` after shifting them by the bootstrap's bias estimate
    (their mean minus ``value``), so that it brackets ``value`` with the draws' spread."""
    tail = (1 - level) / 2
    low, high = np.quantile(draws - (draws.mean() - value), [tail, 1 - tail])
    return float(low), float(high)


def fid_interval(real, fake, resamples: int = 50, seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """The interval of :func:`fid_and_interval` alone."""
    return fid_and_interval(real, fake, resamples, seed, level)[1:]


def fid_and_interval(real, fake, resamples: int = 50, seed: int = 0,
                     level: float = 0.95) -> tuple[float, float, float]:
    """(FID, low, high): :func:`fid` from the sets' Gram matrices (equal to it to about 1e-12 relative)
    and its percentile bootstrap interval over images: each of ``resamples`` draws resamples
    both sets with replacement (numpy generator seeded with ``seed``) and recomputes the FID from the
    sets' Gram matrices (:func:`_fid_from_grams` on the draw's distinct rows with their counts, one
    SVD per draw). A set that repeats feature vectors is reduced to its distinct vectors with their
    counts first (:func:`_distinct_rows`; the same resamples, values equal to rounding). The draws'
    SVDs run with one BLAS thread each, in parallel for larger sets (:func:`_one_blas_thread_each`).

    A resample repeats images, so it holds fewer distinct ones, and FID grows as n shrinks: the draws
    sit above the FID of the sets themselves (by 15% at n = 30-40, D = 12, in the tests). The
    interval is therefore bias-corrected: the draws are shifted by the bootstrap's estimate of that
    bias (their mean minus the FID of the sets) before their percentiles are taken, so it brackets
    the estimate and has the spread of the draws. Needs at least 2 rows per set and ``resamples`` >= 2
    (ValueError); the interval is (nan, nan) when ``resamples`` is 0.
    """
    x, y = _pair(real, fake, 2, "FID")
    _check_fid_resamples(resamples)
    (xs, of_x, counts_x), (ys, of_y, counts_y) = _distinct_rows(x.numpy()), _distinct_rows(y.numpy())
    g_xx, g_yy, g_xy = xs @ xs.T, ys @ ys.T, xs @ ys.T
    value = _fid_from_grams(g_xx, g_yy, g_xy, counts_x, counts_y)
    if resamples == 0:
        return value, math.nan, math.nan
    rng = np.random.default_rng(seed)
    n, m = len(of_x), len(of_y)
    weights = [(np.bincount(of_x[rng.integers(0, n, n)], minlength=len(xs)),
                np.bincount(of_y[rng.integers(0, m, m)], minlength=len(ys))) for _ in range(resamples)]

    def draw(counts) -> float:
        i, j = np.flatnonzero(counts[0]), np.flatnonzero(counts[1])
        return _fid_from_grams(g_xx[np.ix_(i, i)], g_yy[np.ix_(j, j)], g_xy[np.ix_(i, j)],
                               counts[0][i].astype(np.float64), counts[1][j].astype(np.float64))

    draws = np.array(_one_blas_thread_each(draw, weights, parallel=len(xs) + len(ys) >= FID_PARALLEL_ROWS))
    low, high = _bias_corrected_interval(draws, value, level)
    return value, max(low, 0.0), max(high, 0.0)


def paired_fid_difference(real, fake_a, fake_b, resamples: int = 50, seed: int = 0,
                          level: float = 0.95) -> tuple[float, float, float]:
    """(FID(real, a) - FID(real, b), low, high): the difference of two candidates' FIDs against one shared
    reference, with a percentile bootstrap interval in which each draw resamples the reference **once for
    both** (and each candidate on its own), so the noise that the shared reference adds to both FIDs
    cancels in the difference (a paired comparison; two candidates' separate intervals both carry it and
    overlap more often than their difference is uncertain). Draws are bias-corrected as in
    :func:`fid_and_interval`. Negative: ``a`` is closer to ``real``. Same checks as there; (nan, nan)
    interval when ``resamples`` is 0."""
    x, a = _pair(real, fake_a, 2, "FID")
    b = _pair(real, fake_b, 2, "FID")[1]
    _check_fid_resamples(resamples)
    sets = [_distinct_rows(v.numpy()) for v in (x, a, b)]
    (xs, _, cx), (as_, _, ca), (bs, _, cb) = sets
    g_xx, g_aa, g_bb, g_xa, g_xb = xs @ xs.T, as_ @ as_.T, bs @ bs.T, xs @ as_.T, xs @ bs.T
    value = _fid_from_grams(g_xx, g_aa, g_xa, cx, ca) - _fid_from_grams(g_xx, g_bb, g_xb, cx, cb)
    if resamples == 0:
        return value, math.nan, math.nan
    rng = np.random.default_rng(seed)
    weights = [tuple(np.bincount(of[rng.integers(0, len(of), len(of))], minlength=len(rows)).astype(np.float64)
                     for rows, of, _ in sets) for _ in range(resamples)]

    def draw(counts) -> float:
        i, j, k = (np.flatnonzero(c) for c in counts)
        w_x, w_a, w_b = counts[0][i], counts[1][j], counts[2][k]
        return (_fid_from_grams(g_xx[np.ix_(i, i)], g_aa[np.ix_(j, j)], g_xa[np.ix_(i, j)], w_x, w_a)
                - _fid_from_grams(g_xx[np.ix_(i, i)], g_bb[np.ix_(k, k)], g_xb[np.ix_(i, k)], w_x, w_b))

    rows = len(xs) + len(as_) + len(bs)
    draws = np.array(_one_blas_thread_each(draw, weights, parallel=rows >= FID_PARALLEL_ROWS))
    return (value, *_bias_corrected_interval(draws, value, level))


def paired_kid_difference(real, fake_a, fake_b, subsets: int = 100, subset_size: int | None = None,
                          seed: int = 0) -> tuple[float, float]:
    """(mean, std) over subsets of KID(real, a) - KID(real, b) with **the same reference subset** for both
    candidates in each draw (:func:`kid`'s cubic kernel and unbiased MMD^2): the reference's own kernel
    sum then cancels exactly, so what is left is the candidates' difference and their own noise. Each draw
    takes ``subset_size`` rows of each set without replacement (default the smallest set, at most 1,000),
    from torch's generator seeded with ``seed`` inside ``fork_rng``. Negative: ``a`` is closer."""
    x, a = _pair(real, fake_a, 2, "KID")
    b = _pair(real, fake_b, 2, "KID")[1]
    if isinstance(subsets, bool) or not isinstance(subsets, int) or subsets < 1:
        raise ValueError(f"KID subsets must be an integer >= 1, got {subsets!r}")
    largest = min(len(x), len(a), len(b))
    size = min(largest, 1000) if subset_size is None else subset_size
    if isinstance(size, bool) or not isinstance(size, int) or not 2 <= size <= largest:
        raise ValueError(f"KID subset_size must be an integer in [2, {largest}] (the smallest set), got {size!r}")
    xs, as_, bs = (v.double().numpy() for v in (x, a, b))
    dim = xs.shape[1]
    k_aa, k_bb, k_xa, k_xb = (_cube(p @ q.T / dim + 1.0) for p, q in ((as_, as_), (bs, bs), (xs, as_), (xs, bs)))
    scores = np.empty(subsets)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        for s in range(subsets):
            r, i, j = (torch.randperm(n)[:size].numpy() for n in (len(xs), len(as_), len(bs)))
            sub_aa, sub_bb = k_aa[np.ix_(i, i)], k_bb[np.ix_(j, j)]
            within = (sub_aa.sum() - np.trace(sub_aa) - sub_bb.sum() + np.trace(sub_bb)) / (size * (size - 1))
            scores[s] = within - 2 * (k_xa[np.ix_(r, i)].sum() - k_xb[np.ix_(r, j)].sum()) / size ** 2
    return float(scores.mean()), float(scores.std())


# --------------------------------------------------------------------------- power spectrum

def _grey(images: torch.Tensor) -> np.ndarray:
    """BT.601 luma in [0, 1], float64, N x H x W."""
    rgb = images.detach().cpu().numpy().astype(np.float64) / 255.0
    return np.einsum("nchw,c->nhw", rgb, np.asarray(LUMA))


def _log_spectra(images: torch.Tensor) -> np.ndarray:
    """Per-image log10 radial power profiles of uint8-range RGB images (float64), N x (min(H, W) // 2)."""
    _check_images(images, "images")
    n, _, h, w = images.shape
    if min(h, w) < MIN_SPECTRUM_SIDE:
        raise ValueError(f"the power spectrum needs images of at least {MIN_SPECTRUM_SIDE} x {MIN_SPECTRUM_SIDE}, "
                         f"got {w} x {h}")
    if n == 0:
        raise ValueError("the power spectrum needs at least 1 image, got 0")
    return log_radial_profiles(torch.from_numpy(_grey(images))).numpy()


def log_spectra(images: torch.Tensor) -> np.ndarray:
    """Per-image profiles N x (S // 2) of :func:`radial_power_spectrum`, which is their mean over the images
    (so a caller can compute each image's profile once and average any subset)."""
    return _log_spectra(images)


def radial_power_spectrum(images: torch.Tensor) -> np.ndarray:
    """Mean over images of the log10 azimuthally averaged power spectrum of their greyscale (Durall et al. 2020, CVPR).

    Per image: grey = BT.601 luma / 255; a periodic Hann window w; the window-weighted mean is
    subtracted (removes brightness, the DC term); P = |FFT2(w * (grey - mean))|^2 / sum(w^2), a
    power spectral density that white noise of variance s^2 gives as s^2 at any image size.
    Frequencies are binned by radius in cycles per pixel: bin k = round(S * |f|) for
    k = 1 .. S // 2, S = min(H, W) (bin k is centred on k / S cycles/px; the corners beyond
    Nyquist are left out). The profile is log10(mean P in bin + Q), with Q = (1/255)^2 / 12 =
    1.28e-6 the PSD of uint8 rounding noise as a floor, so a flat image has the finite profile
    log10(Q) = -5.89 everywhere. Averaging logs, not powers, biases bins with few frequencies
    low (white noise: -0.03 decades over all bins at 32 px, 0.02 at 128 px), alike for any two
    sets of one size. Returns float64 of length S // 2.
    Needs at least one image of at least 8 x 8 (ValueError).
    """
    return _log_spectra(images).mean(axis=0)


def spectrum_distance(real: torch.Tensor, fake: torch.Tensor) -> float:
    """Mean absolute difference (in decades of power) between the :func:`radial_power_spectrum` profiles of two image sets.

    0 for sets of equal mean log profile; blur lowers the high-frequency bins and a flat image
    sits at the rounding-noise floor, so both show as large distances. Both sets need the same
    H x W (ValueError otherwise) and at least one image each.
    """
    _check_images(real, "real")
    _check_images(fake, "fake")
    if real.shape[-2:] != fake.shape[-2:]:
        raise ValueError(f"spectrum_distance needs images of one size, got {tuple(real.shape[-2:])} and {tuple(fake.shape[-2:])}")
    return float(np.mean(np.abs(radial_power_spectrum(real) - radial_power_spectrum(fake))))


# --------------------------------------------------------------------------- two-sample test

@dataclass(frozen=True)
class TwoSampleResult:
    """Held-out accuracy of a real-vs-fake classifier, its n and its 95% Wilson interval [low, high]; ``folds`` used."""

    accuracy: float
    n_test: int
    low: float
    high: float
    folds: int = 0


def _row_keys(rows: np.ndarray) -> list[bytes]:
    """One key per row of a float array, equal exactly when the rows are equal as numbers (-0.0 as 0.0)."""
    rows = np.ascontiguousarray(rows + 0.0)  # -0.0 + 0.0 is 0.0: rows equal as numbers get equal bytes
    return [row.tobytes() for row in rows]


def _fold_groups(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Group ids that put every feature vector occurring in both sets (an exact duplicate) into one group."""
    stacked = np.concatenate([x, y])
    if not set(_row_keys(x)) & set(_row_keys(y)):  # the usual case: no vector in both sets, no sort needed
        return np.arange(len(stacked)) + len(stacked)
    _, inverse = np.unique(stacked, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    shared = np.intersect1d(inverse[:len(x)], inverse[len(x):])
    groups = np.arange(len(stacked)) + len(stacked)
    in_both = np.isin(inverse, shared)
    groups[in_both] = inverse[in_both]
    return groups


def standardised_ridge_predict(train: np.ndarray, labels: np.ndarray, test: np.ndarray,
                               alpha: float = 1.0) -> np.ndarray:
    """0/1 predictions for ``test`` of a linear least-squares classifier with an L2 penalty ``alpha``,
    trained on float64 ``train`` rows with 0/1 ``labels`` after per-feature standardisation.

    The model of scikit-learn's ``make_pipeline(StandardScaler(), RidgeClassifier(alpha))``, in closed
    form: features scaled by the training rows' mean and population standard deviation (a constant
    feature keeps scale 1); targets -1 / +1; intercept by centring; weights
    w = X^T (X X^T + alpha I)^-1 y when there are more features than rows (the dual form), else
    (X^T X + alpha I)^-1 X^T y; class 1 where X w + b > 0. Agrees with scikit-learn's predictions
    (tested) at a fraction of its per-call overhead (1,320 calls in a score stage)."""
    mean, variance = train.mean(axis=0), train.var(axis=0)
    eps, n = np.finfo(np.float64).eps, len(train)
    # constant within the rounding of a two-pass variance (Chan, Golub & LeVeque 1983), as scikit-learn decides
    constant = variance <= n * eps * variance + (n * mean * eps) ** 2
    std = np.where(constant, 1.0, np.sqrt(variance))
    x = (train - mean) / std
    target = np.where(labels == 1, 1.0, -1.0)
    x_mean, y_mean = x.mean(axis=0), target.mean()
    xc, yc = x - x_mean, target - y_mean
    if xc.shape[1] > xc.shape[0]:
        weights = xc.T @ np.linalg.solve(xc @ xc.T + alpha * np.eye(len(xc)), yc)
    else:
        weights = np.linalg.solve(xc.T @ xc + alpha * np.eye(xc.shape[1]), xc.T @ yc)
    scores = ((test - mean) / std) @ weights + (y_mean - x_mean @ weights)
    return (scores > 0).astype(np.int64)


def two_sample_test(real, fake, seed: int = 0, folds: int = 5) -> TwoSampleResult:
    """Classifier two-sample test (Lopez-Paz & Oquab 2017, ICLR): how well can real and fake features be told apart?

    The larger set is subsampled (without replacement, ``seed``) to the smaller one's n, so the
    classes are balanced and chance is 0.5. A pipeline of per-feature standardisation and a linear
    L2-regularised least-squares classifier (:func:`standardised_ridge_predict`, alpha 1: closed
    form; logistic regression with lbfgs took 0.42 s per call at n = 72, D = 704, because on
    separable sets its weights never converge, and 10 of the score stage's 46 s) is trained and tested in stratified
    k-fold cross-validation (k = min(folds, n), shuffled with ``seed``); the predictions of all
    folds are pooled, so ``n_test`` = 2 n (every image is predicted once, by a model that did
    not see it). A feature vector found in both sets (an exact duplicate) is kept in one fold, so
    a copy never teaches the model the opposite label of its own test twin. The interval is the
    Wilson score interval on ``n_test`` (it treats the pooled predictions as independent, an
    approximation).

    Values: 0.5 = indistinguishable, 1.0 = perfectly separable; values below 0.5 are noise
    (read them as 0.5). Identical sets give exactly 0.5. If all 2 n vectors are one and the same
    (e.g. equal constant images), there is nothing to learn and the accuracy is 0.5 by
    definition (``folds`` = 0). A training fold that holds only one class predicts that class.
    Needs at least 2 rows per set (ValueError).
    """
    x_t, y_t = _pair(real, fake, 2, "the two-sample test")
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"folds must be an integer >= 2, got {folds!r}")
    rng = np.random.default_rng(seed)
    n = min(len(x_t), len(y_t))
    x = x_t.numpy()[np.sort(rng.choice(len(x_t), n, replace=False))]
    y = y_t.numpy()[np.sort(rng.choice(len(y_t), n, replace=False))]
    data = np.concatenate([x, y])
    labels = np.repeat([1, 0], n)
    if bool((data == data[0]).all()):  # one vector, repeated
        low, high = wilson_interval(0.5, 2 * n)
        return TwoSampleResult(0.5, 2 * n, low, high, 0)

    from sklearn.model_selection import StratifiedGroupKFold, StratifiedKFold

    groups = _fold_groups(x, y)
    k = min(folds, n, len(np.unique(groups)))
    # the group-aware splitter is needed only when a vector occurs in both sets, and it is slow
    # (a greedy pass per group: 80 ms per call at n = 72), so plain stratified folds otherwise
    shared = len(np.unique(groups)) < len(groups)
    splitter = (StratifiedGroupKFold if shared else StratifiedKFold)(
        n_splits=k, shuffle=True, random_state=int(seed) % 2 ** 32)
    predicted = np.empty(2 * n, dtype=np.int64)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*least populated class.*")
        for train, test in splitter.split(data, labels, groups if shared else None):
            classes = np.unique(labels[train])
            if len(classes) == 1:
                predicted[test] = classes[0]
                continue
            predicted[test] = standardised_ridge_predict(data[train], labels[train], data[test])
    accuracy = float((predicted == labels).mean())
    low, high = wilson_interval(accuracy, 2 * n)
    # the shared Wilson function can land one ulp inside the observed share at 0 or 1
    return TwoSampleResult(accuracy, 2 * n, min(low, accuracy), max(high, accuracy), k)


# --------------------------------------------------------------------------- PRDC

def prdc_scores(real, fake, k: int = 5) -> dict[str, float]:
    """Precision, recall (Kynkäänniemi et al. 2019, NeurIPS), density and coverage (Naeem et al. 2020, ICML).

    Each real (fake) point gets a ball whose radius is the distance to its k-th nearest real
    (fake) neighbour, itself excluded. precision = share of fake points inside some real ball;
    recall = share of real points inside some fake ball; density = mean number of real balls
    holding a fake point, / k (1 on average for matching distributions, can exceed 1); coverage =
    share of real balls holding at least one fake point. Euclidean distances, strict ``<``.

    Computed here in torch, with the definitions and conventions of the authors' ``prdc`` package
    (tests agree with it to 1e-12), for a measured reason: ``prdc`` 0.2 computes its distances
    through scikit-learn with ``n_jobs=8``, whose thread pool spent 22 of 100 s waiting in the
    score stage of the default run on 2 cores (312 calls), against about 1 ms per call here.
    Distances go through one matrix product each, and every radius and every ``<`` that the
    product's rounding could decide differently is settled on the exact (direct) distances
    (:class:`_BoundedDistances`), so the scores are those of the direct distances, bit for bit.

    Like ``prdc``, k is at most n - 2 for both sets, so k is lowered to min(k, n_real - 2,
    n_fake - 2); the k used is returned as ``"k"``. Needs at least 3 rows per set (ValueError). A
    set of identical points has balls of radius 0: as fake it gets recall 0, as real precision 0
    and density 0.
    """
    x, y = _pair(real, fake, 3, "PRDC")
    if isinstance(k, bool) or not isinstance(k, int) or k < 1:
        raise ValueError(f"PRDC k must be an integer >= 1, got {k!r}")
    used = min(k, len(x) - 2, len(y) - 2)
    x, y = x.double(), y.double()
    # the (used + 1)-th smallest distance, counting the point itself at distance 0
    real_radius, fake_radius = (_BoundedDistances(p, p).kth_smallest(used + 1) for p in (x, y))
    between = _BoundedDistances(x, y)                           # real x fake
    inside_real = between.less_than(real_radius[:, None])       # fake j inside real ball i
    scores = {"precision": inside_real.any(dim=0).double().mean(),
              "recall": between.less_than(fake_radius[None, :]).any(dim=1).double().mean(),
              "density": inside_real.sum(dim=0).double().mean() / used,
              # a real ball holds a fake point exactly when its nearest fake point is inside it
              "coverage": inside_real.any(dim=1).double().mean()}
    return {**{name: float(value) for name, value in scores.items()}, "k": float(used)}


# --------------------------------------------------------------------------- memorisation

@dataclass(frozen=True)
class MemorisationResult:
    """Memorisation check; see :func:`memorisation`. Distances are per generated image."""

    rate: float
    reference_rate: float
    nearest_is_train_share: float
    nearest_is_train_reference: float
    threshold: float
    n_generated: int
    n_train: int
    n_heldout: int
    distance_to_train: np.ndarray
    distance_to_heldout: np.ndarray


def _rows(values, name: str) -> torch.Tensor:
    if isinstance(values, torch.Tensor) and values.ndim == 4:
        values = values.reshape(len(values), -1)  # images: flattened pixels
    return _as_features(values, name, 1, "the memorisation check")


def _distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.cdist(a, b, compute_mode="donot_use_mm_for_euclid_dist")  # exact: a copy is at distance 0


_UNIT_ROUNDOFF = 2.0 ** -53
EXACT_PAIRS = 4096  # pairs per batched direct-distance call of _BoundedDistances.exact (two 4096 x D copies)


class _BoundedDistances:
    """Euclidean distances between the rows of float64 ``a`` (N x D) and ``b`` (M x D) through one matrix
    product, |a|^2 + |b|^2 - 2 a.b (10-100x faster than the direct difference at D in the hundreds),
    with a bound on how far each can be from :func:`_distances` (the direct difference, which a copy
    puts at exactly 0), so that the nearest-neighbour decisions can be made exactly: an order or a
    ``<`` the bound cannot settle is decided on the direct distance of that entry alone (torch's direct
    distance of a pair does not depend on the other rows or on batching: tested).

    The bound (standard rounding analysis, u = 2^-53, then doubled): the product form's squared
    distance is within (D + 3) u (|a| + |b|)^2 of the true one, so its root within
    sqrt((D + 3) u) (|a| + |b|); the direct distance is within (D + 4) u |a - b| of the true one."""

    def __init__(self, a: torch.Tensor, b: torch.Tensor):
        self.a, self.b = a, b
        norms_a, norms_b = a.square().sum(1), b.square().sum(1)
        self.approx = (norms_a[:, None] + norms_b[None, :] - 2 * (a @ b.T)).clamp_min_(0).sqrt_()
        d = a.shape[1]
        factor = 2 * (math.sqrt((d + 3) * _UNIT_ROUNDOFF) + (d + 6) * _UNIT_ROUNDOFF)
        self.bound = factor * (norms_a.sqrt()[:, None] + norms_b.sqrt()[None, :])
        if not (torch.isfinite(self.approx).all() and torch.isfinite(self.bound).all()):  # overflow: direct
            self.approx, self.bound = _distances(a, b), torch.zeros(len(a), len(b), dtype=a.dtype)

    def exact(self, rows: torch.Tensor, columns: torch.Tensor) -> torch.Tensor:
        """The direct distances of the pairs (rows[p], columns[p]), as a batch of 1 x 1 direct distances
        (``EXACT_PAIRS`` pairs per call)."""
        values = torch.empty(len(rows), dtype=self.approx.dtype)
        for start in range(0, len(rows), EXACT_PAIRS):
            r, c = rows[start:start + EXACT_PAIRS], columns[start:start + EXACT_PAIRS]
            values[start:start + len(r)] = _distances(self.a[r].unsqueeze(1), self.b[c].unsqueeze(1))[:, 0, 0]
        return values

    def kth_smallest(self, k: int, columns: torch.Tensor | None = None, skip_diagonal: bool = False) -> torch.Tensor:
        """Per row, the k-th smallest direct distance (``_distances(a, b).kthvalue(k, dim=1)``), over
        ``columns`` only when given, leaving out entry (i, i) when ``skip_diagonal`` (a against itself);
        +inf where a row has fewer than k such entries. Only the entries whose lower bound is at most the
        k-th smallest upper bound of their row can be among the k smallest: those are computed directly."""
        approx, bound = self.approx, self.bound
        if columns is not None:
            approx, bound = approx[:, columns], bound[:, columns]
        upper, lower = approx + bound, approx - bound
        if skip_diagonal:
            index = torch.arange(len(self.a)) if columns is None else columns
            off = index[None, :] == torch.arange(len(self.a))[:, None]
            upper, lower = upper.masked_fill(off, math.inf), lower.masked_fill(off, math.inf)
        if upper.shape[1] < k:
            return torch.full((len(self.a),), math.inf, dtype=approx.dtype)
        limit = upper.kthvalue(k, dim=1).values
        candidates = (lower <= limit[:, None]) & (lower < math.inf)  # a left-out entry is never one
        rows, picked = candidates.nonzero(as_tuple=True)
        values = torch.full_like(approx, math.inf)
        values[rows, picked] = self.exact(rows, picked if columns is None else columns[picked])
        return values.kthvalue(k, dim=1).values

    def less_than(self, thresholds: torch.Tensor) -> torch.Tensor:
        """``_distances(a, b) < thresholds`` (broadcast to N x M), decided on the direct distance wherever
        the bound leaves it open."""
        thresholds = thresholds.expand_as(self.approx)
        below = self.approx + self.bound < thresholds
        unsure = ~below & (self.approx - self.bound < thresholds)
        if unsure.any():
            rows, columns = unsure.nonzero(as_tuple=True)
            below[rows, columns] = self.exact(rows, columns) < thresholds[rows, columns]
        return below


PIXEL_BLOCK = 1024  # pixels per float32 product in pixel_squared_distances: |partial sums| <= 1024 * 128^2 = 2^24


def pixel_squared_distances(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Squared Euclidean distances between the flattened pixels of uint8 images ``a`` (N x ...) and ``b``
    (M x ...): float64 N x M, exact integers. |a'|^2 + |b'|^2 - 2 a'.b' with a' = a - 128 (a shift leaves
    distances alone and puts every product within 128^2); the products run in float32 on blocks of
    ``PIXEL_BLOCK`` pixels, where every partial sum is an integer of magnitude at most 2^24 and so
    exact, and the blocks add up in float64 (exact below 2^53): the integers a float64 product gives, in
    about half its time. Where torch may lower float32 products' precision
    (``torch.get_float32_matmul_precision()`` other than "highest") the product runs in float64."""
    x, y = (v.reshape(len(v), -1) for v in (a, b))
    if torch.get_float32_matmul_precision() != "highest":
        x, y = x.to(torch.float64), y.to(torch.float64)
        return x.square().sum(1)[:, None] + y.square().sum(1)[None, :] - 2 * (x @ y.T)
    x, y = x.to(torch.float32) - 128.0, y.to(torch.float32) - 128.0
    dot = torch.zeros(len(x), len(y), dtype=torch.float64)
    part = torch.empty(len(x), len(y), dtype=torch.float32)
    for start in range(0, x.shape[1], PIXEL_BLOCK):
        torch.mm(x[:, start:start + PIXEL_BLOCK].contiguous(), y[:, start:start + PIXEL_BLOCK].contiguous().T, out=part)
        dot += part
    norms_x, norms_y = x.to(torch.float64).square().sum(1), y.to(torch.float64).square().sum(1)
    return norms_x[:, None] + norms_y[None, :] - 2 * dot


def pairwise_distances(a, b) -> torch.Tensor:
    """Euclidean distances (float64 ``N x M``) between the rows of ``a`` and ``b``: features ``N x D``
    (tensors or arrays), or images ``N x C x H x W`` (flattened to pixels).

    Exact in both cases, so a copy is at distance 0: uint8 images go through the exact integer matrix
    product of :func:`pixel_squared_distances`, 10-100x faster than a direct difference at image
    dimensions; features
    through torch's direct difference (``donot_use_mm_for_euclid_dist``). ValueError when the
    dimensions differ or a set is empty.
    """
    if all(isinstance(v, torch.Tensor) and v.dtype == torch.uint8 and v.ndim == 4 for v in (a, b)):
        if not len(a) or not len(b) or a.shape[1:] != b.shape[1:]:
            raise ValueError(f"pairwise_distances needs non-empty image sets of one size, got {tuple(a.shape)} "
                             f"and {tuple(b.shape)}")
        return pixel_squared_distances(a, b).clamp_min_(0).sqrt_()
    x, y = _rows(a, "a"), _rows(b, "b")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"pairwise_distances needs one dimension D, got {x.shape[1]} and {y.shape[1]}")
    return _distances(x, y)


def memorisation(generated, train, heldout) -> MemorisationResult:
    """Are generated images closer to the training images than real images the generator never saw?

    Inputs are ``N x D`` features (or images, ``N x C x H x W``, flattened to pixels); Euclidean
    distances (:func:`pairwise_distances`). d_T(z) is the distance from z to its nearest training
    image, d_H(z) to its nearest held-out real image.

    * ``rate``: share of generated g with d_T(g) < ``threshold`` = min over held-out h of d_T(h),
      i.e. closer to the training set than any held-out real image is. ``reference_rate``: the
      same for each held-out h_i against the threshold of the *other* held-out images (leave
      one out); for exchangeable real images this is exactly 1 / n_heldout without ties (only
      the closest one passes), and a new real image passes with probability 1 / (n_heldout + 1).
      A rate well above that flags copies of training images.
    * ``nearest_is_train_share``: share of generated g whose nearest real image (train and
      held-out together) is a training one, d_T(g) < d_H(g). ``nearest_is_train_reference``: the
      same for each held-out h_i among train and the other held-out images; it carries the
      share a real image gets from the sizes of the two sets alone.

    Ties count as "not train" (a generated image equally close to both is not flagged). A copy of
    the training set gives rate 1 and share 1 (unless a held-out image equals a training image,
    which makes the threshold 0). With 1 held-out image the leave-one-out references are NaN.
    Needs at least one row in each set and one dimension D (ValueError).
    """
    def rows(values, name):
        if isinstance(values, torch.Tensor) and values.dtype == torch.uint8 and values.ndim == 4 and len(values):
            return values  # uint8 images: pairwise_distances takes the exact integer route
        return _rows(values, name)

    g, t, h = rows(generated, "generated"), rows(train, "train"), rows(heldout, "heldout")
    dims = [math.prod(v.shape[1:]) for v in (g, t, h)]
    if len(set(dims)) > 1:
        raise ValueError(f"the memorisation check needs one dimension D, got {dims[0]} (generated), "
                         f"{dims[1]} (train), {dims[2]} (heldout)")
    if len({v.dtype for v in (g, t, h)}) > 1:  # images beside features: compare all as float64 rows
        g, t, h = _rows(g, "generated"), _rows(t, "train"), _rows(h, "heldout")
    return memorisation_from_distances(pairwise_distances(g, t), pairwise_distances(g, h),
                                       pairwise_distances(h, t), pairwise_distances(h, h))


def memorisation_from_distances(g_train, g_held, h_train, h_held) -> MemorisationResult:
    """:func:`memorisation` from its four distance matrices (generated x train, generated x held-out,
    held-out x train, held-out x held-out; the diagonal of the last is ignored)."""
    if min(g_train.shape[0], g_train.shape[1], h_train.shape[0]) == 0:
        raise ValueError("the memorisation check needs at least one generated, train and held-out image")
    h_h = h_held.clone()
    h_h.fill_diagonal_(math.inf)
    return memorisation_from_nearest(g_train.min(dim=1).values, g_held.min(dim=1).values,
                                     h_train.min(dim=1).values, h_h.min(dim=1).values, int(g_train.shape[1]))


def memorisation_from_nearest(g_train, g_held, h_train, h_held, n_train: int) -> MemorisationResult:
    """:func:`memorisation` from each image's nearest distances (float64 tensors): generated to train,
    generated to held-out, held-out to train, held-out to the *other* held-out images (+inf where there is
    none), e.g. from :func:`nearest_distances`, so that a caller can compute them once for a whole set and
    read the rows of each class; ``n_train``: the size of the training set they were taken over."""
    if min(len(g_train), int(n_train), len(h_train)) == 0:
        raise ValueError("the memorisation check needs at least one generated, train and held-out image")
    threshold = float(h_train.min())
    rate = float((g_train < threshold).double().mean())
    share = float((g_train < g_held).double().mean())
    n_h = len(h_train)
    if n_h > 1:
        others = h_train.repeat(n_h, 1)
        others.fill_diagonal_(math.inf)
        reference_rate = float((h_train < others.min(dim=1).values).double().mean())
        reference_share = float((h_train < h_held).double().mean())
    else:
        reference_rate = reference_share = math.nan
    return MemorisationResult(rate, reference_rate, share, reference_share, threshold, len(g_train), int(n_train),
                              n_h, g_train.numpy(), g_held.numpy())


def nearest_distances(a, b, groups=None, skip_diagonal: bool = False) -> dict:
    """Per row of ``a``, the distance to its nearest row of ``b`` (inputs as :func:`pairwise_distances`):
    ``{None: over all rows of b}``, plus one entry per label of ``groups`` (one label per row of b): over
    the rows of b with that label (+inf where there is none). ``skip_diagonal``: ``a`` is ``b`` and a row's
    own entry is left out. Float64 tensors equal bit for bit to the minima of :func:`pairwise_distances`'s
    rows (or of its blocks of columns): images through its exact integer product, features through
    :class:`_BoundedDistances` (one matrix product, the direct distance only where the nearest is in doubt)."""
    labels = {None: None}
    if groups is not None:
        groups = np.asarray(groups)
        labels.update({label: torch.from_numpy(np.flatnonzero(groups == label)) for label in np.unique(groups)})
    images = all(isinstance(v, torch.Tensor) and v.dtype == torch.uint8 and v.ndim == 4 for v in (a, b))
    if images:
        full = pairwise_distances(a, b)
        if skip_diagonal:
            full.fill_diagonal_(math.inf)

        def nearest(columns):
            block = full if columns is None else full[:, columns]
            if block.shape[1] == 0:
                return torch.full((len(full),), math.inf, dtype=full.dtype)
            return block.min(dim=1).values
    else:
        x, y = _rows(a, "a"), _rows(b, "b")
        if x.shape[1] != y.shape[1]:
            raise ValueError(f"nearest_distances needs one dimension D, got {x.shape[1]} and {y.shape[1]}")
        bounded = _BoundedDistances(x, y)

        def nearest(columns):
            return bounded.kth_smallest(1, columns, skip_diagonal)
    return {label: nearest(columns) for label, columns in labels.items()}


# --------------------------------------------------------------------------- diversity

DIVERSITY_SIDE = 64  # the pixel view of the diversity ratio: greyscale at 64 x 64


def grey_pixels(images: torch.Tensor, side: int = DIVERSITY_SIDE) -> torch.Tensor:
    """uint8 ``N x 3 x H x W`` -> float64 ``N x side^2``: BT.601 luma in grey levels [0, 255], resized
    to ``side`` x ``side`` (area average) when the images have another size."""
    _check_images(images, "images")
    grey = torch.einsum("nchw,c->nhw", images.to(torch.float64), torch.tensor(LUMA, dtype=torch.float64))
    if grey.shape[-2:] != (side, side):
        grey = F.interpolate(grey[:, None], size=(side, side), mode="area")[:, 0]
    return grey.reshape(len(images), -1)


@dataclass(frozen=True)
class DiversityResult:
    """Within-set spread of generated and real images and their ratio with a 95% bootstrap interval; see :func:`diversity_ratio`."""

    ratio: float
    low: float
    high: float
    generated_spread: float
    real_spread: float
    n_generated: int
    n_real: int


def _mean_off_diagonal(distances: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Mean of distances[index_p, index_q] over the pairs p != q whose draws are distinct images, per row
    of ``index`` (B x n draws); NaN where no such pair exists."""
    block = distances[index[:, :, None], index[:, None, :]]
    distinct = index[:, :, None] != index[:, None, :]
    counts = distinct.sum(axis=(1, 2))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, (block * distinct).sum(axis=(1, 2)) / np.maximum(counts, 1), np.nan)


def diversity_ratio(generated, real, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> DiversityResult:
    """Within-class diversity of generated images against real ones: mean pairwise distance among
    ``generated`` over the mean pairwise distance among ``real`` (Euclidean, features ``N x D``, or
    images, whose pixels are compared as given: pass :func:`grey_pixels` for the 64 px grey view).

    1 when the generated images spread as much as real ones (a resample of the real set gives about
    1), 0 when they are all one image (mode collapse: a generator that ignores its input). The
    interval is a percentile bootstrap over images: both sets are resampled with replacement
    (``resamples`` draws, numpy generator seeded with ``seed``), and a draw's spread averages the pairs
    of distinct images only, so repeated draws of one image do not count as zero distances. Needs at
    least 2 rows per set (ValueError); the ratio is NaN when every real image is the same.
    """
    x, y = _as_features(generated, "generated", 2, "the diversity ratio"), _as_features(real, "real", 2, "the diversity ratio")
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"the diversity ratio needs one dimension D, got {x.shape[1]} and {y.shape[1]}")
    d_g, d_r = _distances(x, x).numpy(), _distances(y, y).numpy()
    spread_g = float(d_g[~np.eye(len(x), dtype=bool)].mean())
    spread_r = float(d_r[~np.eye(len(y), dtype=bool)].mean())
    ratio = spread_g / spread_r if spread_r > 0 else math.nan
    low = high = math.nan
    if resamples and spread_r > 0:
        rng = np.random.default_rng(seed)
        draws = []
        for chunk in range(0, int(resamples), 100):  # chunks keep the B x n x n blocks small
            count = min(100, int(resamples) - chunk)
            g = _mean_off_diagonal(d_g, rng.integers(0, len(x), (count, len(x))))
            r = _mean_off_diagonal(d_r, rng.integers(0, len(y), (count, len(y))))
            with np.errstate(invalid="ignore", divide="ignore"):
                draws.append(np.where(r > 0, g / r, np.nan))
        draws = np.concatenate(draws)
        draws = draws[np.isfinite(draws)]
        if len(draws):
            tail = (1 - level) / 2
            low, high = (float(v) for v in np.quantile(draws, [tail, 1 - tail]))
    return DiversityResult(ratio, low, high, spread_g, spread_r, len(x), len(y))


def median_interval(values, resamples: int = 1000, seed: int = 0, level: float = 0.95) -> tuple[float, float, float]:
    """(median, low, high) of ``values`` (e.g. one ratio per class; NaN ignored) with a percentile bootstrap
    interval over the values (resampled with replacement); NaNs when none is finite, (m, m, m) for one."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return math.nan, math.nan, math.nan
    median = float(np.median(values))
    if len(values) == 1:
        return median, median, median
    draws = np.median(values[np.random.default_rng(seed).integers(0, len(values), (resamples, len(values)))], axis=1)
    tail = (1 - level) / 2
    low, high = np.quantile(draws, [tail, 1 - tail])
    return median, float(low), float(high)


# --------------------------------------------------------------------------- baselines

def default_blur_sigma(side: int) -> float:
    """The blur vtgen's 'blurred real' baseline uses: sigma = side / 32 (2 px at 64 px, 8 px at 256 px)."""
    return float(side) * BLUR_FRACTION


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """Gaussian blur of uint8 ``N x 3 x H x W`` images: uint8 out, same shape.

    Separable float64 convolution with taps exp(-t^2 / (2 sigma^2)), t = -r .. r, r =
    min(ceil(4 sigma), min(H, W) - 1) (truncated at 4 sigma, as scipy does, and at the image
    side), normalised to sum 1; reflect padding (mirror about the edge pixel: torch's
    ``reflect``, OpenCV's BORDER_REFLECT_101); rounded half to even and clipped to [0, 255].
    ``sigma`` 0 returns a copy; negative or non-finite sigma is a ValueError. vtgen's default is
    :func:`default_blur_sigma` (side / 32).
    """
    _check_images(images, "images")
    if not (isinstance(sigma, (int, float)) and math.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"sigma must be a finite number >= 0, got {sigma!r}")
    if sigma == 0 or len(images) == 0:
        return images.clone()
    h, w = images.shape[-2:]
    radius = min(math.ceil(4 * sigma), min(h, w) - 1)
    if radius < 1:
        return images.clone()
    t = torch.arange(-radius, radius + 1, dtype=torch.float64)
    taps = torch.exp(-t ** 2 / (2 * sigma ** 2))
    taps = taps / taps.sum()
    x = images.to(torch.float64).reshape(-1, 1, h, w)
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="reflect"), taps.view(1, 1, 1, -1))
    x = F.conv2d(F.pad(x, (0, 0, radius, radius), mode="reflect"), taps.view(1, 1, -1, 1))
    return x.round().clamp(0, 255).to(torch.uint8).reshape(images.shape)


def flat_colour_set(images: torch.Tensor, n: int | None = None) -> torch.Tensor:
    """``n`` (default len(images)) copies of one flat image of the mean colour of ``images`` (rounded), uint8."""
    _check_images(images, "images")
    if len(images) == 0:
        raise ValueError("a flat colour needs at least 1 image, got 0")
    colour = images.to(torch.float64).mean(dim=(0, 2, 3)).round().to(torch.uint8)
    count = len(images) if n is None else int(n)
    return colour.view(1, 3, 1, 1).expand(count, 3, *images.shape[-2:]).clone()


def mean_image_set(images: torch.Tensor, n: int | None = None) -> torch.Tensor:
    """``n`` (default len(images)) copies of the pixel-wise mean image of ``images`` (rounded), uint8."""
    _check_images(images, "images")
    if len(images) == 0:
        raise ValueError("a mean image needs at least 1 image, got 0")
    mean = images.to(torch.float64).mean(dim=0).round().to(torch.uint8)
    count = len(images) if n is None else int(n)
    return mean.unsqueeze(0).expand(count, *mean.shape).clone()
