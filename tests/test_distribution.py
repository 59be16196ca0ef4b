"""Distribution metrics (vtgen.core.distribution): references, extremes, and the ranking real > blur that SSIM misses."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import scipy.ndimage
import scipy.spatial
import torch
import torch.nn.functional as F

from vtgen.core import distribution as dist
from vtgen.core.classifier import AlexNet
from vtgen.core.metrics import pairwise_colour_ssim

VITAC = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "vitac_cloth11"


# --------------------------------------------------------------------------- helpers

def textures(n: int, size: int = 64, seed: int = 0, classes: int = 3) -> torch.Tensor:
    """Textured uint8 images of a few 'classes': coloured oriented gratings with random phase, frequency jitter and noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64)
    colours = np.array([[180, 90, 60], [70, 140, 200], [120, 170, 90]], dtype=np.float64)
    out = np.empty((n, 3, size, size), dtype=np.uint8)
    for i in range(n):
        c = i % classes
        angle = np.pi * c / classes + rng.normal(0, 0.1)
        freq = (0.08 + 0.06 * c) * rng.uniform(0.9, 1.1)
        wave = np.sin(2 * np.pi * freq * (np.cos(angle) * xx + np.sin(angle) * yy) + rng.uniform(0, 2 * np.pi))
        grey = 40 * wave + rng.normal(0, 12, (size, size))
        out[i] = np.clip(colours[c][:, None, None] + grey[None], 0, 255).round().astype(np.uint8)
    return torch.from_numpy(out)


def numpy_kid_reference(x: np.ndarray, y: np.ndarray, subsets: int, size: int, seed: int) -> tuple[float, float]:
    """Unbiased MMD^2 with k = (a.b / D + 1)^3 over the subsets torch's generator draws after manual_seed(seed)."""
    gen_state = torch.random.get_rng_state()
    torch.manual_seed(seed)
    values = []
    for _ in range(subsets):
        a = x[torch.randperm(len(x)).numpy()[:size]]
        b = y[torch.randperm(len(y)).numpy()[:size]]
        kernel = lambda p, q: (p @ q.T / x.shape[1] + 1.0) ** 3  # noqa: E731
        kaa, kbb, kab = kernel(a, a), kernel(b, b), kernel(a, b)
        m = size
        values.append((kaa.sum() - np.trace(kaa)) / (m * (m - 1)) + (kbb.sum() - np.trace(kbb)) / (m * (m - 1))
                      - 2 * kab.mean())
    torch.random.set_rng_state(gen_state)
    return float(np.mean(values)), float(np.std(values))


def numpy_fid_reference(x: np.ndarray, y: np.ndarray) -> float:
    s1, s2 = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    root = scipy.linalg.sqrtm(s1 @ s2)
    return float(((x.mean(0) - y.mean(0)) ** 2).sum() + np.trace(s1 + s2 - 2 * root.real))


def load_tiles(folder: Path, size: int | None = 64) -> torch.Tensor:
    """uint8 N x 3 x size x size tiles, resized as vtgen's tile reader does (area when shrinking)."""
    from PIL import Image

    tiles = []
    for path in sorted(folder.glob("*.jpg")):
        array = np.array(Image.open(path).convert("RGB"))
        batch = torch.from_numpy(array).permute(2, 0, 1)[None].float()
        if size is not None and batch.shape[-1] != size:
            batch = F.interpolate(batch, size=(size, size), mode="area")
        tiles.append(batch.round().clamp(0, 255).to(torch.uint8))
    return torch.cat(tiles)


@pytest.fixture(scope="module")
def encoder() -> dist.RandomEncoder:
    return dist.RandomEncoder()


# --------------------------------------------------------------------------- encoders

def test_random_encoder_is_deterministic_and_pinned(encoder):
    images = textures(6, size=32)
    first = dist.image_features(encoder, images)
    assert first.dtype == torch.float64 and first.shape == (6, encoder.num_features) == (6, 704)
    assert torch.equal(first, dist.image_features(encoder, images))
    rebuilt = dist.RandomEncoder()
    assert torch.equal(first, dist.image_features(rebuilt, images))
    # the weights come from an explicit generator: pinned values catch a changed draw order or seed
    assert float(encoder.weight0.sum()) == pytest.approx(8.882261276245117, abs=1e-5)
    assert encoder.weight0.flatten()[:3].tolist() == pytest.approx([-0.30641481, -0.31363273, -0.06819885], abs=1e-7)
    assert float(encoder.weight3.sum()) == pytest.approx(-25.830806732177734, abs=1e-4)
    other = dist.image_features(dist.RandomEncoder(seed=1), images)
    assert not torch.allclose(first, other)
    assert not list(encoder.parameters())  # nothing to train


def test_random_encoder_inputs(encoder):
    assert dist.image_features(encoder, textures(2, size=16)).shape == (2, 704)
    wide = torch.randint(0, 256, (2, 3, 24, 40), dtype=torch.uint8)
    assert dist.image_features(encoder, wide).shape == (2, 704)
    with pytest.raises(ValueError, match="at least 16"):
        encoder(torch.zeros(1, 3, 15, 32, dtype=torch.uint8))
    with pytest.raises(ValueError, match="uint8"):
        encoder(torch.zeros(1, 3, 32, 32))
    with pytest.raises(ValueError, match="uint8"):
        dist.image_features(encoder, torch.zeros(1, 1, 32, 32, dtype=torch.uint8))
    assert dist.image_features(encoder, torch.zeros(0, 3, 32, 32, dtype=torch.uint8)).shape == (0, 704)


def test_image_features_batches_agree(encoder):
    images = textures(5, size=32)
    one = dist.image_features(encoder, images, batch_size=1)
    assert torch.allclose(one, dist.image_features(encoder, images, batch_size=64), rtol=1e-5, atol=1e-6)


def test_random_encoder_sees_contrast_and_scale(encoder):
    images = textures(4, size=32)
    features = dist.image_features(encoder, images)
    flat = dist.image_features(encoder, dist.flat_colour_set(images))
    stds = slice(encoder.num_features // 2, None)
    assert torch.all(flat[:, stds] == 0)  # a flat image has no spatial variation at any stage
    assert torch.all(features[:, stds].sum(dim=1) > 0)


def test_classifier_encoder_gives_fc7_activations():
    torch.manual_seed(0)
    model = AlexNet(3, size=32, width=0.125)
    model.train()
    images = textures(5, size=32)
    captured = {}
    hook = model.classifier.relu7.register_forward_hook(lambda m, i, o: captured.setdefault("fc7", o.clone()))
    model.eval()
    with torch.no_grad():
        model(images)
    hook.remove()
    model.train()
    encoder = dist.classifier_encoder(model)
    features = dist.image_features(encoder, images, batch_size=2)
    assert features.shape == (5, encoder.num_features) == (5, model.classifier.fc7.out_features)
    assert torch.allclose(features, captured["fc7"].double(), atol=1e-5)
    assert model.training  # mode restored
    assert torch.allclose(features, dist.image_features(dist.PenultimateFeatures(model), images), atol=1e-6)
    with pytest.raises(ValueError, match="trained on 32 x 32"):
        dist.image_features(encoder, textures(2, size=64))
    with pytest.raises(ValueError, match="AlexNet"):
        dist.classifier_encoder(dist.RandomEncoder())


# --------------------------------------------------------------------------- KID

def test_kid_matches_numpy_reference():
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=(40, 12)), rng.normal(0.3, 1.2, size=(30, 12))
    mean, std = dist.kid(torch.from_numpy(x), torch.from_numpy(y), subsets=20, subset_size=15, seed=3)
    ref_mean, ref_std = numpy_kid_reference(x, y, 20, 15, 3)
    assert mean == pytest.approx(ref_mean, rel=1e-6, abs=1e-9)
    assert std == pytest.approx(ref_std, rel=1e-6, abs=1e-9)
    assert mean > 0.05  # shifted distributions


class PassThrough(torch.nn.Module):
    """Identity 'feature extractor', so that torchmetrics' FID and KID take precomputed features."""

    def __init__(self, num_features: int):
        super().__init__()
        self.num_features = num_features

    def forward(self, x):
        return x


def test_kid_equals_torchmetrics_on_the_same_subset_draws():
    import warnings

    from torchmetrics.image.kid import KernelInceptionDistance

    rng = np.random.default_rng(6)
    x, y = rng.normal(size=(40, 12)), rng.normal(0.2, 1.1, size=(33, 12))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        metric = KernelInceptionDistance(feature=PassThrough(12), subsets=25, subset_size=16)
    metric.update(torch.from_numpy(x), real=True)
    metric.update(torch.from_numpy(y), real=False)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(7)
        theirs = [float(v) for v in metric.compute()]
    ours = dist.kid(torch.from_numpy(x), torch.from_numpy(y), subsets=25, subset_size=16, seed=7)
    assert ours == pytest.approx(theirs, rel=1e-9, abs=1e-12)


def test_kid_is_reproducible_and_leaves_global_rng_alone():
    rng = np.random.default_rng(2)
    x, y = rng.normal(size=(30, 5)), rng.normal(size=(30, 5))
    state = torch.random.get_rng_state()
    first = dist.kid(x, y, subsets=10, subset_size=10, seed=0)
    assert torch.equal(state, torch.random.get_rng_state())
    assert dist.kid(x, y, subsets=10, subset_size=10, seed=0) == first
    assert dist.kid(x, y, subsets=10, subset_size=10, seed=1) != first


def test_kid_extremes():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(100, 8))
    with pytest.raises(ValueError, match="KID needs at least 2 images per set, got 1"):
        dist.kid(x[:1], x)
    with pytest.raises(ValueError, match="subset_size"):
        dist.kid(x[:5], x, subset_size=6)
    with pytest.raises(ValueError, match="NaN"):
        dist.kid(np.full((3, 8), np.nan), x)
    with pytest.raises(ValueError, match="dimension"):
        dist.kid(x[:, :4], x)
    # identical sets, subsets smaller than the set: 0 within the noise of the subsets
    mean, std = dist.kid(x, x, subsets=50, subset_size=50)
    assert abs(mean) < 3 * std + 1e-3
    # identical sets, whole set in every subset: exactly -2/n (mean diagonal - mean off-diagonal kernel), std 0
    small = x[:10]
    kernel = (small @ small.T / 8 + 1) ** 3
    off = (kernel.sum() - np.trace(kernel)) / 90
    mean, std = dist.kid(small, small)
    assert mean == pytest.approx(-2 / 10 * (np.trace(kernel) / 10 - off), rel=1e-9) and mean <= 0 and std <= 1e-12
    for n in (2, 3):
        value, _ = dist.kid(x[:n], x[50:50 + n] + 1.0, subsets=5)
        assert math.isfinite(value)
    # constant and zero-variance features; different n
    constant = np.full((6, 8), 0.5)
    assert dist.kid(constant, constant, subsets=3) == (0.0, 0.0)
    assert dist.kid(constant, constant + 1, subsets=3)[0] > 0
    zero_var = x[:20].copy()
    zero_var[:, 3] = 7.0
    assert math.isfinite(dist.kid(zero_var, x[20:60], subsets=5)[0])
    assert math.isfinite(dist.kid(x[:7], x[7:60], subsets=5)[0])  # subset_size defaults to the smaller n


# --------------------------------------------------------------------------- FID

def test_fid_matches_scipy_reference_and_torchmetrics():
    from torchmetrics.image.fid import FrechetInceptionDistance

    rng = np.random.default_rng(4)
    x = rng.normal(size=(200, 10))
    y = rng.normal(0.5, 1.5, size=(150, 10)) + rng.normal(size=(150, 10)) @ rng.normal(size=(10, 10)) * 0.3
    value = dist.fid(torch.from_numpy(x), torch.from_numpy(y))
    assert value == pytest.approx(numpy_fid_reference(x, y), rel=1e-6)
    metric = FrechetInceptionDistance(feature=PassThrough(10))
    metric.update(torch.from_numpy(x), real=True)
    metric.update(torch.from_numpy(y), real=False)
    assert value == pytest.approx(float(metric.compute()), rel=1e-6)


def test_fid_extremes():
    rng = np.random.default_rng(5)
    with pytest.raises(ValueError, match="FID needs at least 2 images per set, got 1"):
        dist.fid(rng.normal(size=(1, 4)), rng.normal(size=(5, 4)))
    # identical sets with singular covariances (n <= D): 0, where an eigenvalue square root gives -2.7e-5
    for n in (2, 3, 15):
        x = rng.uniform(size=(n, 704)) * 100
        assert abs(dist.fid(x, x)) <= 1e-6
        assert abs(dist.fid(x, x[::-1].copy())) <= 1e-6
    # constant sets: |c_r - c_f|^2
    assert dist.fid(np.full((4, 3), 2.0), np.full((6, 3), 3.0)) == pytest.approx(3.0, abs=1e-12)
    # zero-variance feature columns and different n, against the reference with the column dropped
    x, y = rng.normal(size=(60, 6)), rng.normal(size=(40, 6)) * 2
    x[:, 2], y[:, 2] = 1.0, 1.5
    expected = numpy_fid_reference(np.delete(x, 2, 1), np.delete(y, 2, 1)) + 0.25
    assert dist.fid(x, y) == pytest.approx(expected, rel=1e-6)
    # D > n, distinct sets: finite and positive
    assert dist.fid(rng.normal(size=(3, 50)), rng.normal(size=(2, 50)) + 1) > 0


# --------------------------------------------------------------------------- power spectrum

def test_spectrum_definition():
    rng = np.random.default_rng(6)
    flat = torch.full((3, 3, 32, 32), 120, dtype=torch.uint8)
    profile = dist.radial_power_spectrum(flat)
    assert profile.shape == (16,)
    assert np.allclose(profile, math.log10(dist.QUANTISATION_PSD))
    # white noise of variance s^2 has PSD s^2 at every size: the profile does not depend on the size
    levels = []
    for size in (32, 128):
        noise = torch.from_numpy(rng.normal(128, 20, (20, 1, size, size)).round().clip(0, 255).astype(np.uint8)).repeat(1, 3, 1, 1)
        profile = dist.radial_power_spectrum(noise)
        levels.append(profile[len(profile) // 2:].mean())  # bins with many frequencies: little log bias
    expected = math.log10((20 / 255) ** 2 + dist.QUANTISATION_PSD)
    assert levels[0] == pytest.approx(expected, abs=0.03) and levels[1] == pytest.approx(expected, abs=0.03)
    # brightness: a constant offset does not change the profile
    images = (textures(4, size=32) // 2 + 60).to(torch.uint8)  # 60 .. 187
    darker = images - 50
    assert np.allclose(dist.radial_power_spectrum(images), dist.radial_power_spectrum(darker), atol=1e-9)


def test_spectrum_distance_extremes():
    images = textures(6)
    assert dist.spectrum_distance(images, images) == 0.0
    assert dist.spectrum_distance(images[:1], images[1:2]) >= 0  # n = 1 is defined
    blurred = dist.gaussian_blur(images, 2.0)
    real_profile, blur_profile = dist.radial_power_spectrum(images), dist.radial_power_spectrum(blurred)
    assert (blur_profile[16:] < real_profile[16:] - 1).all()  # blur removes high frequencies
    with pytest.raises(ValueError, match="one size"):
        dist.spectrum_distance(images, textures(2, size=32))
    with pytest.raises(ValueError, match="at least 8"):
        dist.radial_power_spectrum(torch.zeros(1, 3, 7, 7, dtype=torch.uint8))
    with pytest.raises(ValueError, match="at least 1 image"):
        dist.radial_power_spectrum(torch.zeros(0, 3, 32, 32, dtype=torch.uint8))


# --------------------------------------------------------------------------- two-sample test

def test_two_sample_extremes():
    rng = np.random.default_rng(7)
    x = rng.normal(size=(40, 6))
    with pytest.raises(ValueError, match="two-sample test needs at least 2 images per set, got 1"):
        dist.two_sample_test(x[:1], x)
    same = dist.two_sample_test(x, x)
    assert same.accuracy == 0.5 and same.n_test == 80 and same.low < 0.5 < same.high
    shuffled = dist.two_sample_test(x, x[rng.permutation(40)])
    assert shuffled.accuracy == 0.5
    far = dist.two_sample_test(x, x + 5)
    assert far.accuracy == 1.0 and far.low > 0.9
    for n in (2, 3):
        result = dist.two_sample_test(x[:n], x[20:20 + n] + 5)
        assert result.n_test == 2 * n and 0 <= result.accuracy <= 1 and result.low <= result.accuracy <= result.high
    constant = np.full((5, 6), 1.0)
    degenerate = dist.two_sample_test(constant, constant)
    assert degenerate.accuracy == 0.5 and degenerate.folds == 0
    assert dist.two_sample_test(constant, constant + 1).accuracy == 1.0
    unequal = dist.two_sample_test(x[:7], rng.normal(size=(30, 6)))
    assert unequal.n_test == 14
    zero_var = x.copy()
    zero_var[:, 0] = 3.0
    assert dist.two_sample_test(zero_var, zero_var + np.r_[0, 10, 0, 0, 0, 0]).accuracy == 1.0
    other = rng.normal(size=(40, 6))
    assert dist.two_sample_test(x, other, seed=1) == dist.two_sample_test(x, other, seed=1)  # seeded


def test_two_sample_same_distribution_is_near_chance():
    rng = np.random.default_rng(8)
    result = dist.two_sample_test(rng.normal(size=(100, 8)), rng.normal(size=(100, 8)))
    assert result.low <= 0.5 <= result.high
    assert dist.two_sample_test(rng.normal(size=(100, 8)), rng.normal(size=(100, 8)), seed=3).n_test == 200


# --------------------------------------------------------------------------- PRDC

def test_prdc_extremes():
    rng = np.random.default_rng(9)
    x = rng.normal(size=(30, 5))
    with pytest.raises(ValueError, match="PRDC needs at least 3 images per set, got 2"):
        dist.prdc_scores(x[:2], x)
    same = dist.prdc_scores(x, x)
    assert same["precision"] == same["recall"] == same["coverage"] == 1.0 and same["k"] == 5
    assert dist.prdc_scores(x[:3], x[10:13])["k"] == 1
    assert dist.prdc_scores(x, x[:6])["k"] == 4
    collapsed = dist.prdc_scores(x, np.repeat(x.mean(0, keepdims=True), 10, axis=0))
    assert collapsed["recall"] == 0.0 and collapsed["coverage"] < 1.0  # one point covers only the balls around it
    far = dist.prdc_scores(x, x + 100)
    assert far == {"precision": 0.0, "recall": 0.0, "density": 0.0, "coverage": 0.0, "k": 5.0}


# --------------------------------------------------------------------------- memorisation

def test_memorisation_definitions():
    rng = np.random.default_rng(10)
    train, heldout, fresh = rng.normal(size=(40, 6)), rng.normal(size=(20, 6)), rng.normal(size=(30, 6))
    copy = dist.memorisation(train.copy(), train, heldout)
    assert copy.rate == 1.0 and copy.nearest_is_train_share == 1.0
    assert copy.reference_rate == pytest.approx(1 / 20)  # leave one out: only the closest held-out image passes
    assert (copy.distance_to_train == 0).all()
    assert (copy.n_generated, copy.n_train, copy.n_heldout) == (40, 40, 20)
    real = dist.memorisation(fresh, train, heldout)
    assert real.rate <= 0.2 and real.nearest_is_train_share < 0.95
    # the leave-one-out share: each held-out image's nearest among train and the other held-out images
    d_train = scipy.spatial.distance.cdist(heldout, train).min(1)
    d_held = scipy.spatial.distance.cdist(heldout, heldout)
    np.fill_diagonal(d_held, np.inf)
    assert real.nearest_is_train_reference == pytest.approx(float((d_train < d_held.min(1)).mean()))
    lone = dist.memorisation(fresh, train, heldout[:1])
    assert math.isnan(lone.reference_rate) and math.isnan(lone.nearest_is_train_reference)
    assert lone.threshold == pytest.approx(d_train[0])


def test_memorisation_inputs():
    images = textures(6, size=16)
    result = dist.memorisation(images[:2], images[:4], images[4:])  # images are flattened to pixels
    assert result.rate == 1.0 and result.nearest_is_train_share == 1.0
    with pytest.raises(ValueError, match="one dimension"):
        dist.memorisation(np.zeros((2, 3)), np.zeros((2, 4)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match="at least 1 images per set, got 0 in heldout"):
        dist.memorisation(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((0, 3)))


# --------------------------------------------------------------------------- blur and baselines

def test_gaussian_blur_matches_scipy_mirror():
    images = textures(2, size=32)
    out = dist.gaussian_blur(images, 1.5)
    assert out.dtype == torch.uint8 and out.shape == images.shape
    reference = scipy.ndimage.gaussian_filter(images.double().numpy(), sigma=(0, 0, 1.5, 1.5), mode="mirror", truncate=4.0)
    assert np.abs(out.int().numpy() - np.round(reference)).max() <= 1
    assert torch.equal(dist.gaussian_blur(images, 0), images)
    constant = torch.full((1, 3, 20, 20), 77, dtype=torch.uint8)
    assert torch.equal(dist.gaussian_blur(constant, 50.0), constant)  # kernel cut at the image side, still exact
    with pytest.raises(ValueError, match="sigma"):
        dist.gaussian_blur(images, -1.0)
    assert dist.default_blur_sigma(64) == 2.0 and dist.default_blur_sigma(256) == 8.0


def test_baseline_sets():
    images = textures(5, size=16)
    flat = dist.flat_colour_set(images, 3)
    assert flat.shape == (3, 3, 16, 16) and flat.dtype == torch.uint8
    assert torch.equal(flat[0, :, 0, 0], images.double().mean(dim=(0, 2, 3)).round().to(torch.uint8))
    assert (flat == flat[:, :, :1, :1]).all()
    mean = dist.mean_image_set(images)
    assert mean.shape == images.shape and torch.equal(mean[0], images.double().mean(0).round().to(torch.uint8))


# --------------------------------------------------------------------------- ranking real > blur

def check_ranking(encoder, reference: torch.Tensor, real: torch.Tensor) -> dict:
    """Every new metric ranks ``real`` (held-out) above a flat colour, the mean image and blurred real images."""
    side = reference.shape[-1]
    n = len(real)
    baselines = {"flat colour": dist.flat_colour_set(reference, n), "mean image": dist.mean_image_set(reference, n),
                 "blurred real": dist.gaussian_blur(real, dist.default_blur_sigma(side))}
    ref_features = dist.image_features(encoder, reference)
    scores = {}
    for name, images in {"real": real, **baselines}.items():
        features = dist.image_features(encoder, images)
        prdc = dist.prdc_scores(ref_features, features)
        scores[name] = {"kid": dist.kid(ref_features, features)[0], "fid": dist.fid(ref_features, features),
                        "spectrum": dist.spectrum_distance(reference, images),
                        "two_sample": dist.two_sample_test(ref_features, features).accuracy,
                        "recall": prdc["recall"], "coverage": prdc["coverage"]}
    for name in baselines:
        for metric in ("kid", "fid", "spectrum", "two_sample"):
            assert scores["real"][metric] < scores[name][metric], (name, metric, scores)
        for metric in ("recall", "coverage"):
            assert scores["real"][metric] > scores[name][metric], (name, metric, scores)
    return scores


@pytest.mark.slow
def test_ranking_on_synthetic_textures(encoder):
    images = textures(60, seed=11)
    check_ranking(encoder, images[::2], images[1::2])
    train, heldout = images[:40], images[40:]
    copied = dist.memorisation(dist.image_features(encoder, train), dist.image_features(encoder, train),
                               dist.image_features(encoder, heldout))
    assert copied.rate == 1.0 > copied.reference_rate


@pytest.fixture(scope="module")
def vitac() -> Path:
    if not VITAC.is_dir():
        pytest.skip(f"real ViTac sample not found at {VITAC} (tests read it from ../shared/data, it is not in the repo)")
    return VITAC


@pytest.mark.slow
@pytest.mark.parametrize("modality", ["t", "v"])
def test_ranking_on_real_vitac(encoder, vitac, modality):
    train, test = load_tiles(vitac / f"11{modality}"), load_tiles(vitac / f"11{modality}_test")
    assert train.shape == (20, 3, 64, 64) and test.shape == (10, 3, 64, 64)
    # two random halves of all 30 real tiles (the sample's own test tiles are one contiguous region:
    # for the visual tiles the two-sample test tells them from the training tiles with accuracy 1.0)
    pooled = torch.cat([train, test])
    perm = torch.randperm(30, generator=torch.Generator().manual_seed(0))
    check_ranking(encoder, pooled[perm[:15]], pooled[perm[15:]])
    # a copy of the training set is caught; real held-out images are not
    features = dist.image_features(encoder, pooled)
    f_train, f_heldout, f_unseen = features[perm[:15]], features[perm[15:25]], features[perm[25:]]
    copied = dist.memorisation(f_train, f_train, f_heldout)
    assert copied.rate == 1.0 and copied.nearest_is_train_share == 1.0
    unseen = dist.memorisation(f_unseen, f_train, f_heldout)
    assert unseen.rate <= 0.2 < copied.rate


@pytest.mark.slow
def test_set_to_set_colour_ssim_fails_the_ranking(vitac):
    """The documented failure: on unaligned real tactile tiles a flat mean colour beats real images in set-to-set SSIM."""
    train, test = load_tiles(vitac / "11t", None), load_tiles(vitac / "11t_test", None)
    channels_last = lambda images: images.permute(0, 2, 3, 1).numpy()  # noqa: E731
    real = pairwise_colour_ssim(channels_last(test), channels_last(train)).mean()
    flat = pairwise_colour_ssim(channels_last(dist.flat_colour_set(train, 1)), channels_last(test)).mean()
    assert real == pytest.approx(0.312, abs=0.002) and flat == pytest.approx(0.450, abs=0.002)
    assert flat > real


def test_prdc_agrees_with_the_authors_package():
    """vtgen computes PRDC itself (the package's thread pool is slow on 2 cores); same numbers as `prdc`."""
    import contextlib
    import io

    prdc = pytest.importorskip("prdc")
    rng = np.random.default_rng(5)
    for n_real, n_fake, k, shift in ((12, 9, 5, 0.3), (30, 30, 5, 0.0), (5, 7, 5, 1.0), (40, 25, 3, 0.5)):
        real = rng.normal(size=(n_real, 16))
        fake = rng.normal(size=(n_fake, 16)) + shift
        ours = dist.prdc_scores(real, fake, k)
        with contextlib.redirect_stdout(io.StringIO()):
            theirs = prdc.compute_prdc(real, fake, nearest_k=int(ours["k"]))
        for name in ("precision", "recall", "density", "coverage"):
            assert ours[name] == pytest.approx(float(theirs[name]), abs=1e-12), (name, n_real, n_fake)


# --------------------------------------------------------------------------- shared pieces of the score stage (issue 26)

def test_fid_from_grams_equals_fid_and_the_bootstrap_interval_brackets_it():
    rng = np.random.default_rng(11)
    x, y = rng.normal(size=(40, 12)), rng.normal(0.3, 1.2, size=(30, 12))
    assert dist._fid_from_grams(x @ x.T, y @ y.T, x @ y.T) == pytest.approx(dist.fid(x, y), rel=1e-9)
    low, high = dist.fid_interval(x, y, resamples=200, seed=0)
    assert low < dist.fid(x, y) < high
    assert dist.fid_interval(x, y, resamples=200, seed=0) == (low, high)  # seeded
    assert all(math.isnan(v) for v in dist.fid_interval(x, y, resamples=0))
    value, *interval = dist.fid_and_interval(x, y, resamples=200, seed=0)
    assert value == pytest.approx(dist.fid(x, y), rel=1e-9) and tuple(interval) == (low, high)
    assert dist.fid_and_interval(x, y, resamples=0)[0] == value
    # more images, narrower interval
    big_x, big_y = rng.normal(size=(400, 12)), rng.normal(0.3, 1.2, size=(300, 12))
    big_low, big_high = dist.fid_interval(big_x, big_y, resamples=100, seed=0)
    assert big_high - big_low < (high - low) / 2
    with pytest.raises(ValueError, match="resamples"):
        dist.fid_interval(x, y, resamples=1)


def test_fid_of_a_draw_with_repeated_rows_equals_fid_of_its_counts():
    """A bootstrap draw is scored on its distinct rows with their counts: the same FID as the rows repeated."""
    rng = np.random.default_rng(12)
    x, y = rng.normal(size=(25, 30)), rng.normal(0.2, 1.1, size=(20, 30))
    i, j = rng.integers(0, 25, 25), rng.integers(0, 20, 20)
    w_x, w_y = np.bincount(i, minlength=25).astype(float), np.bincount(j, minlength=20).astype(float)
    keep_x, keep_y = np.flatnonzero(w_x), np.flatnonzero(w_y)
    xd, yd = x[keep_x], y[keep_y]
    weighted = dist._fid_from_grams(xd @ xd.T, yd @ yd.T, xd @ yd.T, w_x[keep_x], w_y[keep_y])
    assert weighted == pytest.approx(dist.fid(x[i], y[j]), rel=1e-10)
    assert len(keep_x) < 25  # the draw did repeat rows, so the counts mattered


def test_standardised_ridge_predicts_as_scikit_learns_pipeline():
    from sklearn.linear_model import RidgeClassifier
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    rng = np.random.default_rng(13)
    disagreements = 0
    for n, features in ((12, 3), (40, 12), (60, 200), (150, 40)):  # both the primal and the dual form
        x = rng.normal(size=(n, features)) * rng.uniform(0.01, 100, features)
        x[:, 0] = 7.0  # a constant feature keeps scale 1
        labels = np.arange(n) % 2
        x[labels == 1] += 0.3
        test = rng.normal(size=(80, features)) * x.std(axis=0) + x.mean(axis=0)
        theirs = make_pipeline(StandardScaler(), RidgeClassifier(alpha=1.0)).fit(x, labels).predict(test)
        ours = dist.standardised_ridge_predict(x, labels, test)
        disagreements += int((ours != theirs).sum())
        assert set(np.unique(ours)) <= {0, 1}
    assert disagreements == 0


def test_pairwise_distances_are_exact_for_images_and_features():
    images = textures(7, size=16)
    fast = dist.pairwise_distances(images, images[:4])
    direct = torch.cdist(images.flatten(1).double(), images[:4].flatten(1).double(),
                         compute_mode="donot_use_mm_for_euclid_dist")
    assert torch.equal(fast, direct)  # integer pixels: the matrix product is exact
    assert torch.equal(torch.diagonal(fast[:4]), torch.zeros(4, dtype=torch.float64))  # a copy is at distance 0
    features = torch.randn(5, 3, dtype=torch.float64)
    assert torch.allclose(dist.pairwise_distances(features, features[:2]), torch.cdist(features, features[:2]))
    with pytest.raises(ValueError, match="one dimension"):
        dist.pairwise_distances(np.zeros((2, 3)), np.zeros((2, 4)))


def test_memorisation_from_distances_equals_memorisation():
    images = textures(20, size=16)
    g, t, h = images[:6], images[6:14], images[14:]
    whole = dist.memorisation(g, t, h)
    parts = dist.memorisation_from_distances(*(dist.pairwise_distances(a, b) for a, b in ((g, t), (g, h), (h, t), (h, h))))
    assert (parts.rate, parts.reference_rate, parts.nearest_is_train_share, parts.n_train) == \
        (whole.rate, whole.reference_rate, whole.nearest_is_train_share, 8)
    copied = dist.memorisation(t[:3].clone(), t, h)
    assert copied.rate == 1.0


def test_diversity_ratio_known_inputs():
    rng = np.random.default_rng(3)
    real = rng.normal(size=(60, 8))
    # identical generated images: no spread at all (mode collapse)
    collapsed = dist.diversity_ratio(np.repeat(real[:1], 10, axis=0), real, resamples=200)
    assert collapsed.ratio == 0.0 and collapsed.low == collapsed.high == 0.0 and collapsed.n_generated == 10
    # generated = a resample of the real images: about 1, and the interval holds 1
    resample = dist.diversity_ratio(real[rng.integers(0, 60, 60)], real, resamples=500)
    assert 0.85 < resample.ratio < 1.15 and resample.low < 1.0 < resample.high
    # half the spread, exactly: the real images shrunk towards their mean
    half = dist.diversity_ratio(real.mean(0) + 0.5 * (real - real.mean(0)), real, resamples=100)
    assert half.ratio == pytest.approx(0.5, rel=1e-12)
    assert math.isnan(dist.diversity_ratio(real[:3], np.zeros((4, 8)), resamples=10).ratio)  # real without spread
    with pytest.raises(ValueError, match="at least 2 images per set"):
        dist.diversity_ratio(real[:1], real)


def test_grey_pixels_and_median_interval():
    images = torch.zeros(2, 3, 128, 128, dtype=torch.uint8)
    images[:, 0] = 100  # red only: luma 0.299 * 100
    grey = dist.grey_pixels(images)
    assert grey.shape == (2, 64 * 64) and torch.allclose(grey, torch.full_like(grey, 29.9))
    median, low, high = dist.median_interval([0.1, 0.2, 0.3, 0.4, 5.0], resamples=500)
    assert median == 0.3 and low <= median <= high and high <= 5.0
    assert dist.median_interval([0.7]) == (0.7, 0.7, 0.7)
    assert all(math.isnan(v) for v in dist.median_interval([math.nan]))


# --------------------------------------------------------------------------- exact nearest neighbours via one product

def direct(a, b) -> torch.Tensor:
    return torch.cdist(torch.as_tensor(a, dtype=torch.float64), torch.as_tensor(b, dtype=torch.float64),
                       compute_mode="donot_use_mm_for_euclid_dist")


def direct_prdc(real, fake, k: int = 5) -> dict:
    """PRDC as prdc_scores computed it on direct distances before the matrix-product path (the reference)."""
    x, y = torch.as_tensor(real, dtype=torch.float64), torch.as_tensor(fake, dtype=torch.float64)
    used = min(k, len(x) - 2, len(y) - 2)
    real_radius, fake_radius = (direct(p, p).kthvalue(used + 1, dim=1).values for p in (x, y))
    between = direct(x, y)
    inside_real = between < real_radius[:, None]
    return {"precision": float(inside_real.any(dim=0).double().mean()),
            "recall": float((between < fake_radius[None, :]).any(dim=1).double().mean()),
            "density": float(inside_real.sum(dim=0).double().mean() / used),
            "coverage": float((between.min(dim=1).values < real_radius).double().mean()), "k": float(used)}


def tied_features(rng: np.random.Generator, n: int, d: int) -> np.ndarray:
    """Features with exact duplicates, one-hot points at equal distances, and large offsets (rounding-prone)."""
    x = rng.normal(size=(n, d)) + 50.0
    x[: n // 4] = x[n // 4: 2 * (n // 4)]               # exact copies
    x[-3:] = 0.0
    x[-3:, :3] = np.eye(3) * 7.0                        # three points pairwise at the same distance
    return x


def test_bounded_distances_decide_as_the_direct_distances(monkeypatch):
    monkeypatch.setattr(dist, "EXACT_PAIRS", 100)  # several batches of direct pairs
    rng = np.random.default_rng(11)
    for n, m, d in ((30, 40, 700), (9, 5, 3), (25, 25, 1024)):
        a, b = torch.from_numpy(tied_features(rng, n, d)), torch.from_numpy(tied_features(rng, m, d))
        exact = direct(a, b)
        bounded = dist._BoundedDistances(a, b)
        assert ((bounded.approx - exact).abs() <= bounded.bound).all()
        rows, columns = torch.randint(0, n, (50,)), torch.randint(0, m, (50,))
        assert torch.equal(bounded.exact(rows, columns), exact[rows, columns])  # a pair's own direct distance
        for k in (1, 2, 4):
            assert torch.equal(bounded.kth_smallest(k), exact.kthvalue(k, dim=1).values)
        # thresholds at, one ulp below and one ulp above the direct distances: the hardest ties
        for thresholds in (exact, torch.nextafter(exact, torch.tensor(-math.inf, dtype=torch.float64)),
                           torch.nextafter(exact, torch.tensor(math.inf, dtype=torch.float64))):
            assert torch.equal(bounded.less_than(thresholds), exact < thresholds)
        columns = torch.tensor([0, 2, 3])
        assert torch.equal(bounded.kth_smallest(2, columns), exact[:, columns].kthvalue(2, dim=1).values)
        square = torch.cat([a, a[:3]])  # a set against itself, with copies
        itself = direct(square, square).fill_diagonal_(math.inf)
        assert torch.equal(dist._BoundedDistances(square, square).kth_smallest(1, skip_diagonal=True),
                           itself.min(dim=1).values)


def test_prdc_equals_the_direct_distances_bit_for_bit():
    rng = np.random.default_rng(5)
    for n, m, d in ((40, 35, 704), (12, 12, 16), (6, 9, 1024)):
        real, fake = tied_features(rng, n, d), tied_features(rng, m, d)
        for candidate in (fake, real[rng.permutation(n)][:m], np.repeat(fake[:1], m, axis=0), real + 1e-9):
            for k in (1, 5):
                assert dist.prdc_scores(real, candidate, k) == direct_prdc(real, candidate, k)


def test_nearest_distances_equal_the_minima_of_the_pairwise_blocks():
    rng = np.random.default_rng(8)
    images = textures(14, size=16)
    features = torch.from_numpy(tied_features(rng, 14, 300))
    labels = np.array(list("aabbbcccaabbzc"))
    for a, b in ((images[:9], images), (features[:9], features)):
        full = dist.pairwise_distances(a, b) if a.dtype == torch.uint8 else direct(a, b)
        nearest = dist.nearest_distances(a, b, labels)
        assert torch.equal(nearest[None], full.min(dim=1).values)
        for label in set(labels):
            assert torch.equal(nearest[label], full[:, torch.from_numpy(np.flatnonzero(labels == label))].min(dim=1).values)
        own = dist.nearest_distances(b, b, labels, skip_diagonal=True)
        itself = (dist.pairwise_distances(b, b) if b.dtype == torch.uint8 else direct(b, b)).fill_diagonal_(math.inf)
        assert torch.equal(own[None], itself.min(dim=1).values)
        for label in set(labels):
            assert torch.equal(own[label], itself[:, torch.from_numpy(np.flatnonzero(labels == label))].min(dim=1).values)
        assert own["z"][12] == math.inf  # the only "z": no other image of its group
    g, t, h = features[:5], features[5:11], features[11:]
    whole = dist.memorisation(g, t, h)
    parts = dist.memorisation_from_nearest(dist.nearest_distances(g, t)[None], dist.nearest_distances(g, h)[None],
                                           dist.nearest_distances(h, t)[None],
                                           dist.nearest_distances(h, h, skip_diagonal=True)[None], len(t))
    assert (parts.rate, parts.reference_rate, parts.nearest_is_train_share, parts.nearest_is_train_reference,
            parts.threshold) == (whole.rate, whole.reference_rate, whole.nearest_is_train_share,
                                 whole.nearest_is_train_reference, whole.threshold)


def test_fold_groups_without_a_sort_equal_the_sorted_ones():
    def sorted_groups(x, y):  # the groups as computed before the fast path: np.unique over the rows
        stacked = np.concatenate([x, y])
        _, inverse = np.unique(stacked, axis=0, return_inverse=True)
        inverse = inverse.ravel()
        groups = np.arange(len(stacked)) + len(stacked)
        in_both = np.isin(inverse, np.intersect1d(inverse[:len(x)], inverse[len(x):]))
        groups[in_both] = inverse[in_both]
        return groups

    rng = np.random.default_rng(4)
    x, y = rng.normal(size=(12, 5)), rng.normal(size=(9, 5))
    zero_x, zero_y = np.zeros((2, 5)), -np.zeros((1, 5))  # -0.0 equals 0.0: a shared vector
    for a, b in ((x, y), (x, np.concatenate([y, x[3:5]])), (np.concatenate([x, zero_x]), np.concatenate([y, zero_y])),
                 (x, x[:1].repeat(4, axis=0)), (x, y.round(0)), (np.concatenate([x, x[:2]]), y)):
        np.testing.assert_array_equal(dist._fold_groups(a, b), sorted_groups(a, b))


def test_fid_interval_on_distinct_rows_equals_the_draws_on_every_row(monkeypatch):
    def every_row(real, fake, resamples, seed):  # fid_and_interval as computed before the distinct rows
        g_xx, g_yy, g_xy = real @ real.T, fake @ fake.T, real @ fake.T
        value = dist._fid_from_grams(g_xx, g_yy, g_xy)
        rng = np.random.default_rng(seed)
        draws = np.empty(resamples)
        for b in range(resamples):
            i, j = rng.integers(0, len(real), len(real)), rng.integers(0, len(fake), len(fake))
            w_x, w_y = np.bincount(i, minlength=len(real)), np.bincount(j, minlength=len(fake))
            i, j = np.flatnonzero(w_x), np.flatnonzero(w_y)
            draws[b] = dist._fid_from_grams(g_xx[np.ix_(i, i)], g_yy[np.ix_(j, j)], g_xy[np.ix_(i, j)],
                                            w_x[i].astype(np.float64), w_y[j].astype(np.float64))
        draws -= draws.mean() - value
        low, high = np.quantile(draws, [0.025, 0.975])
        return value, max(float(low), 0.0), max(float(high), 0.0)

    rng = np.random.default_rng(9)
    real = rng.normal(size=(40, 30))
    fake = rng.normal(size=(35, 30)) + 0.3
    # every row distinct: the same computation, the same bits
    assert dist.fid_and_interval(real, fake, 20, 3) == every_row(real, fake, 20, 3)
    # repeated vectors (a mean-image baseline: a few images, each many times): equal to rounding
    repeated = np.repeat(fake[:4], [10, 9, 8, 8], axis=0)[rng.permutation(35)]
    for a, b in ((real, repeated), (repeated, real), (np.concatenate([real, real[:5]]), repeated)):
        np.testing.assert_allclose(dist.fid_and_interval(a, b, 20, 3), every_row(a, b, 20, 3), rtol=1e-11, atol=0)
    monkeypatch.setattr(dist, "FID_PARALLEL_ROWS", 0)  # the draws in two threads: the same draws, in order
    np.testing.assert_allclose(dist.fid_and_interval(real, fake, 20, 3), every_row(real, fake, 20, 3), rtol=1e-12)
    value, low, high = dist.fid_and_interval(np.repeat(real[:1], 5, axis=0), repeated, 10)  # one vector: no spread
    assert value == pytest.approx(every_row(np.repeat(real[:1], 5, axis=0), repeated, 10, 0)[0], rel=1e-11)


def test_pixel_squared_distances_are_the_float64_integers(monkeypatch):
    monkeypatch.setattr(dist, "PIXEL_BLOCK", 1024)
    generator = torch.Generator().manual_seed(2)
    a = torch.randint(0, 256, (6, 3, 24, 30), generator=generator, dtype=torch.uint8)  # 2,160 pixels: 3 blocks
    b = torch.cat([torch.randint(0, 256, (4, 3, 24, 30), generator=generator, dtype=torch.uint8),
                   torch.zeros(1, 3, 24, 30, dtype=torch.uint8), torch.full((1, 3, 24, 30), 255, dtype=torch.uint8), a[:1]])
    a[1] = 255  # the extremes: every product at its largest
    x, y = a.flatten(1).double(), b.flatten(1).double()
    expected = x.square().sum(1)[:, None] + y.square().sum(1)[None, :] - 2 * (x @ y.T)
    assert torch.equal(dist.pixel_squared_distances(a, b), expected)
    assert dist.pixel_squared_distances(a, b)[0, 6] == 0  # a copy
    monkeypatch.setattr(torch, "get_float32_matmul_precision", lambda: "medium")  # float64 where float32 may be lowered
    assert torch.equal(dist.pixel_squared_distances(a, b), expected)
    # the nearest-neighbour baseline's choice is torch's Euclidean nearest
    assert torch.equal(dist.pixel_squared_distances(a, b).argmin(dim=1), torch.cdist(x, y).argmin(dim=1))


# --------------------------------------------------------------------------- paired differences (issue 24, goal 2)

def _three_sets(seed: int, shift_b: float = 0.45):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(30, 20)), rng.normal(0.15, 1.0, size=(30, 20)),
            rng.normal(shift_b, 1.0, size=(30, 20)))


def test_paired_fid_difference_resolves_what_two_overlapping_intervals_cannot():
    """Both FIDs carry the shared reference's noise; their difference does not: here the two sets' own
    intervals overlap, the paired difference's interval lies below 0 (a is closer to the reference)."""
    real, a, b = _three_sets(0)
    fid_a, fid_b = dist.fid_and_interval(real, a, 200, 0), dist.fid_and_interval(real, b, 200, 0)
    assert fid_a[0] < fid_b[0] and fid_a[2] > fid_b[1]  # separate intervals overlap
    value, low, high = dist.paired_fid_difference(real, a, b, resamples=200, seed=0)
    assert value == pytest.approx(dist.fid(real, a) - dist.fid(real, b), rel=1e-9)
    assert low < value < high < 0
    assert dist.paired_fid_difference(real, a, b, resamples=200, seed=0) == (value, low, high)  # seeded
    assert math.isnan(dist.paired_fid_difference(real, a, b, resamples=0)[1])
    with pytest.raises(ValueError, match="resamples"):
        dist.paired_fid_difference(real, a, b, resamples=1)


def test_paired_differences_cover_zero_for_candidates_of_one_distribution():
    """No false alarms: a and b drawn from one distribution, 40 trials; the 95% intervals hold 0 in at least 36."""
    fid_hits = kid_hits = 0
    for seed in range(40):
        real, a, b = _three_sets(100 + seed, shift_b=0.15)
        _, low, high = dist.paired_fid_difference(real, a, b, resamples=100, seed=0)
        mean, std = dist.paired_kid_difference(real, a, b, subsets=50, subset_size=15)
        fid_hits += low <= 0 <= high
        kid_hits += mean - 1.96 * std <= 0 <= mean + 1.96 * std
    assert fid_hits >= 36 and kid_hits >= 36


def test_paired_kid_difference_shares_the_reference_subset():
    """Each subset's difference with the reference's kernel terms cancelled, against a direct numpy
    computation on the same draws; and it separates a closer candidate where the two KID spreads overlap."""
    real, a, b = _three_sets(0)
    mean, std = dist.paired_kid_difference(real, a, b, subsets=20, subset_size=15, seed=3)
    kernel = lambda p, q: (p @ q.T / p.shape[1] + 1.0) ** 3  # noqa: E731

    def mmd(x, y):
        k_xx, k_yy = kernel(x, x), kernel(y, y)
        m = len(x)
        return ((k_xx.sum() - np.trace(k_xx)) / (m * (m - 1)) + (k_yy.sum() - np.trace(k_yy)) / (m * (m - 1))
                - 2 * kernel(x, y).mean())

    scores = []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        for _ in range(20):
            r, i, j = (torch.randperm(len(s))[:15].numpy() for s in (real, a, b))
            scores.append(mmd(real[r], a[i]) - mmd(real[r], b[j]))
    assert mean == pytest.approx(np.mean(scores), rel=1e-9, abs=1e-12)
    assert std == pytest.approx(np.std(scores), rel=1e-9, abs=1e-12)
    kid_a, kid_b = dist.kid(real, a, 50, 15), dist.kid(real, b, 50, 15)
    assert kid_a[0] + 1.96 * kid_a[1] > kid_b[0] - 1.96 * kid_b[1]  # separate spreads overlap
    mean, std = dist.paired_kid_difference(real, a, b, subsets=50, subset_size=15)
    assert mean + 1.96 * std < 0
    with pytest.raises(ValueError, match="subset_size"):
        dist.paired_kid_difference(real, a, b[:10], subset_size=15)

