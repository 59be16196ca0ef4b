"""The hand-crafted-feature reader of `conditioning: inferred` (translation.inferred_reader: features)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from sklearn.linear_model import LogisticRegression
from sklearn.preprocessing import StandardScaler

from conftest import TINY_MODEL
from vtgen.core.models import UNetGenerator
from vtgen.core.readers import FEATURE_COUNT, fit_feature_reader, handcrafted_features, SCALE_FLOOR
from vtgen.io.checkpoints import load_translator, save_generator
from vtgen.stages.generate import translate
from vtgen.stages.train import build_conditioning, PairData

HUES = {"red": (200, 50, 40), "green": (40, 170, 60), "blue": (40, 60, 210)}


def tiles(colours: list[tuple[int, int, int]], seed: int, size: int = 32) -> torch.Tensor:
    """One uint8 tile per colour: that colour under a random grey texture (+-20), different per seed. The
    texture is noise, so the reader needs some 30 tiles per class before the texture features average out."""
    rng = np.random.default_rng(seed)
    out = []
    for colour in colours:
        texture = rng.integers(-20, 21, (size, size))
        out.append(np.stack([np.clip(c + texture, 0, 255) for c in colour]))
    return torch.from_numpy(np.stack(out).astype(np.uint8))


def coloured_set(per_class: int, seed: int, names=tuple(HUES)) -> tuple[torch.Tensor, torch.Tensor]:
    colours = [HUES[n] for n in names for _ in range(per_class)]
    return tiles(colours, seed), torch.tensor([i for i in range(len(names)) for _ in range(per_class)])


def test_features_have_the_documented_length_and_see_colour_and_texture():
    a, b = tiles([HUES["red"], HUES["blue"]], seed=0)
    features = handcrafted_features(torch.stack([a, b, a]))
    assert features.shape == (3, FEATURE_COUNT) and np.isfinite(features).all()
    assert np.array_equal(features[0], features[2])  # a function of the pixels only
    assert not np.allclose(features[0, :128], features[1, :128])  # the HSV histogram tells red from blue
    flat = handcrafted_features(torch.full((1, 3, 32, 32), 128, dtype=torch.uint8))[0]
    assert not np.allclose(features[0, 128 + 16:], flat[128 + 16:])  # HOG and LBP see the texture
    with pytest.raises(ValueError, match="uint8 N x 3 x S x S"):
        handcrafted_features(torch.zeros(1, 1, 32, 32, dtype=torch.uint8))


@pytest.mark.parametrize("names", [tuple(HUES), ("red", "blue")])
def test_reader_reads_new_images_and_keeps_scikit_learns_probabilities(names):
    """Fitted on textured tiles whose colour is the class, it reads tiles of another draw right, and its softmax
    equals scikit-learn's predict_proba on the same features (the copied numbers are the fitted model), also
    for two classes, where scikit-learn keeps one row of weights."""
    images, labels = coloured_set(30, seed=1, names=names)
    reader = fit_feature_reader(images, labels, len(names))
    new_images, new_labels = coloured_set(4, seed=2, names=names)
    with torch.no_grad():
        probabilities = torch.softmax(reader(new_images), dim=1).double().numpy()
    assert (probabilities.argmax(axis=1) == new_labels.numpy()).all()
    features = handcrafted_features(images)
    scaler = StandardScaler().fit(features)
    scale = np.maximum(scaler.scale_, SCALE_FLOOR * np.median(scaler.scale_))
    reference = LogisticRegression(C=0.1, max_iter=3000).fit((features - scaler.mean_) / scale, labels.numpy())
    expected = reference.predict_proba((handcrafted_features(new_images) - scaler.mean_) / scale)
    np.testing.assert_allclose(probabilities, expected, atol=1e-5)
    with pytest.raises(ValueError, match="at least 2 classes"):
        fit_feature_reader(images[:3], torch.zeros(3, dtype=torch.int64), 2)


def test_a_feature_that_barely_varies_in_training_moves_a_new_images_reading_little():
    """Three green pixels in one blue training tile give the green hue bins a tiny spread; a new tile with an
    8 x 8 green patch then lands far out on them, and their weights (learnt from that one blue tile) pull its
    reading towards blue. The scale floor (at least SCALE_FLOOR x the median feature's spread) keeps that pull
    under half of what it is without the floor (scale_floor 0), and every new tile is still read by its colour."""
    images, labels = coloured_set(30, seed=1, names=("red", "blue"))
    images[45, :, 0, :3] = torch.tensor(HUES["green"], dtype=torch.uint8)[:, None]  # tile 45 is blue
    new, truth = coloured_set(4, seed=2, names=("red", "blue"))
    patched = new.clone()
    patched[:, :, :8, :8] = torch.tensor(HUES["green"], dtype=torch.uint8)[:, None, None]

    def pull(reader):  # mean change of the blue-minus-red logit that the patch makes
        with torch.no_grad():
            margin = [reader(x)[:, 1] - reader(x)[:, 0] for x in (new, patched)]
            assert torch.equal((margin[1] > 0).long(), truth)
        return float((margin[1] - margin[0]).mean())

    floored = pull(fit_feature_reader(images, labels, 2))
    plain = pull(fit_feature_reader(images, labels, 2, scale_floor=0.0))
    assert plain > 0.5 and floored < plain / 2


def test_a_class_without_training_images_is_never_read():
    images, labels = coloured_set(5, seed=3, names=("red", "blue"))
    reader = fit_feature_reader(images, labels * 2, 3)  # classes 0 and 2 seen, class 1 never
    with torch.no_grad():
        read = reader(coloured_set(3, seed=4, names=tuple(HUES))[0]).argmax(dim=1)
    assert 1 not in read.tolist()


def test_inferred_with_the_feature_reader_reads_the_input_and_survives_the_model_file(tmp_path, capsys):
    """`build_conditioning(..., reader="features")` fits the reader on the training inputs of each class; the
    maps of a test input are those of the class its colour says; a saved model rebuilds the same reader
    (`reader: features` in the settings) and translates the same; an unknown reader is named."""
    inputs, labels = coloured_set(30, seed=5, names=("red", "blue"))
    names = ["red" if int(k) == 0 else "blue" for k in labels]
    data = PairData(inputs.clone(), inputs, names, torch.zeros(len(names), dtype=torch.bool), inputs.clone(),
                    {n: torch.tensor([i for i, k in enumerate(names) if k == n]) for n in ("red", "blue")})
    pairs = pd.DataFrame({"split": "train", "class": names})
    conditioning = build_conditioning("inferred", pairs, "all", data, None, reader="features")
    assert "hand-crafted-feature reader fitted on 60 training inputs of 2 classes" in capsys.readouterr().out
    assert conditioning.classes == ("blue", "red") and conditioning.classifier_settings["reader"] == "features"
    test_images, test_labels = coloured_set(3, seed=6, names=("blue", "red"))
    x = test_images.float() / 127.5 - 1
    maps = conditioning.condition(x, None)[:, 3:, 0, 0]
    assert torch.equal(maps.argmax(dim=1), test_labels)

    generator = UNetGenerator(32, 4, 4, in_channels=3 + conditioning.extra_channels)
    (tmp_path / "model").mkdir()
    save_generator(tmp_path / "model" / "generator.pt", generator, dict(TINY_MODEL, ngf=4), "v2t", "all",
                   conditioning=conditioning)
    loaded_generator, meta = load_translator(tmp_path / "model")
    assert meta["conditioning"].classifier_settings == {"reader": "features", "size": 32}
    assert torch.equal(meta["conditioning"].condition(x, None), conditioning.condition(x, None))
    assert torch.equal(translate(loaded_generator, test_images, conditioning=meta["conditioning"]),
                       translate(generator.eval(), test_images, conditioning=conditioning))
    with pytest.raises(ValueError, match="unknown translation.inferred_reader 'pixels'"):
        build_conditioning("inferred", pairs, "all", data, None, reader="pixels")
