"""Texture classifier and the classify stage: shapes, learning, determinism, fine-tuning, the stage's tables."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from conftest import tiny_params, write_image
from vtgen.core.classifier import (AlexNet, TrainingDiverged, apply_weights, at_chance, first_conv, make_classifier,
                                   train_classifier, wilson_interval)
from vtgen.core.confusion import confusion_counts, realistic_gan_test
from vtgen.io.checkpoints import read_state_dict
from vtgen.io.images import read_tiles
from vtgen.stages.classify import ACCURACY_COLUMNS, low_data_subset, run_classify, SETTINGS
from vtgen.cli import main

TINY = dict(size=32, width=0.125, epochs=3, batch_size=16, lr=0.001)


def stripes(count_per_class: int, seed: int, size: int = 32) -> tuple[torch.Tensor, torch.Tensor]:
    """Three classes of noisy grey stripes: horizontal, vertical, diagonal, with random period and phase."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size]
    images, labels = [], []
    for label, axis in enumerate((yy, xx, xx + yy)):
        for _ in range(count_per_class):
            period, phase = rng.uniform(5, 9), rng.uniform(0, 2 * np.pi)
            wave = 128 + 80 * np.sin(2 * np.pi * axis / period + phase)
            image = np.clip(wave[..., None] + rng.normal(0, 30, (size, size, 3)), 0, 255).astype(np.uint8)
            images.append(image)
            labels.append(label)
    return torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2).contiguous(), torch.tensor(labels)


@pytest.mark.parametrize("size", [32, 64, 227])
def test_alexnet_output_shape_for_sizes_and_widths(size):
    images = torch.randint(0, 256, (2, 3, size, size), dtype=torch.uint8)
    counts = []
    for width in (0.125, 0.25):
        model = AlexNet(5, size, width).eval()
        assert model(images).shape == (2, 5)
        counts.append(sum(p.numel() for p in model.parameters()))
    assert counts[0] < counts[1]
    assert [name for name, m in model.classifier.named_children() if isinstance(m, torch.nn.Linear)] == ["fc6", "fc7", "fc8"]
    if size == 227:
        assert first_conv(227) == (11, 4, 2) and model.pooled_side == 6  # AlexNet's own layout
        assert model.features.conv1.out_channels == 24 and model.classifier.fc6.out_features == 1024


def test_alexnet_refuses_bad_arguments_and_float_images():
    with pytest.raises(ValueError, match="at least 2 classes"):
        AlexNet(1)
    with pytest.raises(ValueError, match="input size"):
        AlexNet(3, size=16)
    with pytest.raises(ValueError, match="uint8"):
        AlexNet(3, 32, 0.125)(torch.zeros(1, 3, 32, 32))


@pytest.mark.slow
def test_classifier_learns_stripe_orientation():
    train_x, train_y = stripes(40, seed=0)
    test_x, test_y = stripes(15, seed=1)
    run = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=4), seed=0,
                           extra_eval={"again": (test_x, test_y)})
    assert len(run.test_accuracy) == len(run.train_loss) == 4
    assert run.test_accuracy[-1] > 0.8  # chance is 1/3
    assert run.train_loss[-1] < run.train_loss[0]
    assert run.extra_accuracy["again"] == run.test_accuracy
    assert not run.model.training and run.seconds > 0


def test_same_seed_same_accuracies_other_seed_other_weights():
    train_x, train_y = stripes(10, seed=0)
    test_x, test_y = stripes(5, seed=1)
    state = torch.get_rng_state()
    first = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=2), seed=3)
    second = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=2), seed=3)
    assert first.test_accuracy == second.test_accuracy and first.train_loss == second.train_loss
    assert torch.equal(torch.get_rng_state(), state)  # the caller's random state is left alone
    same, other = make_classifier(3, TINY, 0), make_classifier(3, TINY, 1)
    assert torch.equal(same.features.conv1.weight, make_classifier(3, TINY, 0).features.conv1.weight)
    assert not torch.equal(same.features.conv1.weight, other.features.conv1.weight)


def reference_training(train_x, train_y, test_x, test_y, extra_x, extra_y, settings, seed, num_classes=3):
    """The training loop written the straightforward way (uint8 batches mirrored and scaled one at a time,
    the default single-tensor Adam, the network run whole for the batch-norm refresh and the
    evaluations): :func:`train_classifier` must give exactly its numbers."""
    import math
    import torch.nn.functional as F
    from vtgen.core.classifier import NORM_IMAGES, scale_images

    def correct_share(model, x, y):
        model.eval()
        with torch.no_grad():
            predicted = model(x).argmax(dim=1)
        return int((predicted == y).sum()) / len(y), predicted

    model = make_classifier(num_classes, settings, seed)
    optimiser = torch.optim.Adam(model.parameters(), lr=settings["lr"], foreach=False)
    sampler, count, batch = torch.Generator().manual_seed(seed), len(train_x), settings["batch_size"]
    test_accuracy, extra_accuracy, losses = [], [], []
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        for _ in range(settings["epochs"]):
            model.train()
            order = torch.randperm(count, generator=sampler)
            mirrored = torch.rand(count, generator=sampler) < 0.5
            total = 0.0
            for start in range(0, count, batch):
                index = order[start:start + batch]
                x = torch.where(mirrored[index].view(-1, 1, 1, 1), train_x[index].flip(-1), train_x[index])
                loss = F.cross_entropy(model(x), train_y[index])
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                total += float(loss.detach()) * len(index)
            losses.append(total / count)
            norms = [m for m in model.features if isinstance(m, torch.nn.BatchNorm2d)]
            for norm in norms:
                norm.reset_running_stats()
                norm.momentum = None
            with torch.no_grad():
                model.features(scale_images(train_x[order[:NORM_IMAGES]]))
            for norm in norms:
                norm.momentum = 0.1
            share, test_predicted = correct_share(model, test_x, test_y)
            test_accuracy.append(share)
            extra_accuracy.append(correct_share(model, extra_x, extra_y)[0])
    assert all(math.isfinite(v) for v in losses)
    return test_accuracy, extra_accuracy, losses, test_predicted, model


@pytest.mark.parametrize("prescale", [True, False])
def test_training_gives_exactly_the_numbers_of_the_straightforward_loop(prescale, monkeypatch):
    """Scaling every set once, the gathered mirror images, the foreach Adam, the shortened batch-norm
    refresh and the kept final predictions change the speed only: accuracies, predictions and
    weights are bit for bit those of the plain loop (with the per-batch fallback too)."""
    import vtgen.core.classifier as classifier

    if not prescale:
        monkeypatch.setattr(classifier, "PRESCALE_BYTES", 0)
    train_x, train_y = stripes(9, seed=0)  # 27 images: batches of 16 and 11
    test_x, test_y = stripes(4, seed=1)
    extra_x, extra_y = stripes(3, seed=2)
    settings = dict(TINY, epochs=3)
    run = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=4, extra_eval={"more": (extra_x, extra_y)})
    test_accuracy, extra_accuracy, losses, predicted, model = reference_training(
        train_x, train_y, test_x, test_y, extra_x, extra_y, settings, seed=4)
    assert run.test_accuracy == test_accuracy and run.extra_accuracy["more"] == extra_accuracy
    assert run.train_loss == pytest.approx(losses, rel=1e-6)  # summed as a tensor here, as Python floats there
    assert torch.equal(run.test_predictions, predicted)
    assert torch.equal(run.extra_predictions["more"], model.eval()(extra_x).argmax(dim=1))
    for (name, mine), theirs in zip(run.model.state_dict().items(), model.state_dict().values()):
        assert torch.equal(mine, theirs), name
    # where the time went, for the stage's images per second
    assert run.train_images == 3 * 27 and run.eval_images == 3 * (12 + 9)
    assert run.train_seconds > 0 and run.eval_seconds > 0 and run.norm_seconds > 0
    assert run.train_seconds + run.eval_seconds + run.norm_seconds <= run.seconds


def test_epoch_images_repeats_whole_passes_and_one_pass_is_the_plain_epoch(monkeypatch):
    """``epoch_images`` = the set's size trains bit for bit as a plain epoch; a larger count is whole
    shuffled passes, each image once per pass, then a cut-short pass, in mini-batches within each pass."""
    import vtgen.core.classifier as classifier

    train_x, train_y = stripes(9, seed=0)  # 27 images
    test_x, test_y = stripes(4, seed=1)
    settings = dict(TINY, epochs=2)
    plain = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=4)
    same = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=4, epoch_images=27)
    assert same.test_accuracy == plain.test_accuracy and same.train_loss == plain.train_loss
    for (name, mine), theirs in zip(same.model.state_dict().items(), plain.model.state_dict().values()):
        assert torch.equal(mine, theirs), name

    drawn = []
    original = classifier._TrainingImages.batch

    def recording(self, order, mirrored, start, size):
        drawn.append(order[start:start + size].tolist())
        return original(self, order, mirrored, start, size)

    monkeypatch.setattr(classifier._TrainingImages, "batch", recording)
    longer = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=4, epoch_images=59)
    assert [len(b) for b in drawn] == [16, 11, 16, 11, 5] * 2  # per epoch: passes of 27, 27, then 5 images
    for epoch in (drawn[:5], drawn[5:]):
        passes = [epoch[0] + epoch[1], epoch[2] + epoch[3], epoch[4]]
        assert sorted(passes[0]) == sorted(passes[1]) == list(range(27)) and len(set(passes[2])) == 5
        assert passes[0] != passes[1]  # a fresh order per pass
    assert longer.train_images == 2 * 59
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="epoch_images"):
            train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=4, epoch_images=bad)
    assert not torch.equal(longer.model.state_dict()["classifier.fc8.weight"], plain.model.state_dict()["classifier.fc8.weight"])


def test_train_classifier_refuses_bad_sets():
    x, y = stripes(2, seed=0)
    with pytest.raises(ValueError, match="at least 2 classes"):
        train_classifier(x, y * 0, x, y * 0, 1, TINY, 0)
    with pytest.raises(ValueError, match="empty"):
        train_classifier(x[:0], y[:0], x, y, 3, TINY, 0)
    with pytest.raises(ValueError, match=r"labels must lie in \[0, 2\]"):
        train_classifier(x, y + 1, x, y, 3, TINY, 0)
    with pytest.raises(ValueError, match="classifier takes 64x64"):
        train_classifier(x, y, x, y, 3, dict(TINY, size=64), 0)


def test_load_weights_retrains_only_the_last_layers(tmp_path):
    source = make_classifier(5, TINY, seed=7)
    torch.save(source.state_dict(), tmp_path / "weights.pt")
    saved = {k: v.clone() for k, v in source.state_dict().items()}
    x, y = stripes(8, seed=0)
    run = train_classifier(x, y, x, y, 3, dict(TINY, epochs=2), seed=0, weights=read_state_dict(tmp_path / "weights.pt"),
                           retrain_layers=2)
    assert run.weights == {"reinitialised": ["classifier.fc8.weight", "classifier.fc8.bias"], "trainable": ["fc7", "fc8"]}
    after = run.model.state_dict()
    for key, value in saved.items():
        if key.startswith(("classifier.fc7.", "classifier.fc8.")):
            continue
        assert torch.equal(after[key], value), f"{key} changed although frozen"  # batch-norm statistics included
    assert not torch.equal(after["classifier.fc7.weight"], saved["classifier.fc7.weight"])
    assert after["classifier.fc8.weight"].shape == (3, source.classifier.fc8.in_features)
    trainable = {name for name, p in run.model.named_parameters() if p.requires_grad}
    assert trainable == {"classifier.fc7.weight", "classifier.fc7.bias", "classifier.fc8.weight", "classifier.fc8.bias"}


def load_weights(model, path, retrain_layers):
    return apply_weights(model, read_state_dict(path), retrain_layers, str(path))


def test_load_weights_errors_name_the_problem(tmp_path):
    model = make_classifier(3, TINY, 0)
    with pytest.raises(ValueError, match="not found"):
        load_weights(model, tmp_path / "missing.pt", 2)
    (tmp_path / "text.pt").write_text("not a torch file")
    with pytest.raises(ValueError, match="not a torch state_dict"):
        load_weights(model, tmp_path / "text.pt", 2)
    torch.save(make_classifier(3, dict(TINY, width=0.25), 0).state_dict(), tmp_path / "wide.pt")
    with pytest.raises(ValueError, match=r"features\.conv1\.weight has shape \(24, 3, 3, 3\) in the file but \(12, 3, 3, 3\)"):
        load_weights(model, tmp_path / "wide.pt", 2)
    torch.save({"conv.weight": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(ValueError, match="features.conv1.weight is missing"):
        load_weights(model, tmp_path / "other.pt", 2)
    with pytest.raises(ValueError, match="retrain_layers"):
        load_weights(model, tmp_path / "wide.pt", 0)


def test_low_data_subset_is_stratified_and_seeded():
    labels = np.repeat([0, 1, 2], [10, 20, 3])
    chosen = low_data_subset(labels, 0.1, seed=0)
    assert np.bincount(labels[chosen]).tolist() == [1, 2, 1]  # at least one per class
    assert np.array_equal(chosen, low_data_subset(labels, 0.1, seed=0))
    assert not np.array_equal(low_data_subset(labels, 0.5, seed=0), low_data_subset(labels, 0.5, seed=1))


CLASSES = ("denim", "felt", "satin")
COLOURS = {"denim": (40, 60, 150), "felt": (150, 40, 40), "satin": (200, 200, 200)}


def fake_layout(root, classes=CLASSES, train=6, test=2, generated_train=3):
    """Real tiles of both modalities (train/val/test), and v2t and t2v tables of generated images under ``root``."""
    rng = np.random.default_rng(0)
    rows = []

    def tile(path, cls):
        noise = rng.normal(0, 25, (32, 32, 3))
        write_image(root / path, np.clip(np.array(COLOURS[cls]) + noise, 0, 255).astype(np.uint8))
        return path

    for cls in classes:
        for modality in ("visual", "tactile"):
            for split, count in (("train", train), ("val", 1), ("test", test)):
                for i in range(count):
                    path = tile(f"data/roi/{modality}/{cls}/{split}{i}.png", cls)
                    rows.append(dict(path=path, **{"class": cls}, modality=modality, source=f"{cls}-{split}{i}",
                                     group=f"{cls}-{split}{i}", split=split))
    splits = pd.DataFrame(rows)
    (root / "data/pairs").mkdir(parents=True)
    splits.to_parquet(root / "data/pairs/splits.parquet")
    for direction, source in (("v2t", "visual"), ("t2v", "tactile")):
        generated = []
        for cls in classes:
            inputs = splits[(splits["modality"] == source) & (splits["class"] == cls)]
            for split, keep in (("train", generated_train), ("test", test)):
                for path in inputs[inputs["split"] == split]["path"].iloc[:keep]:
                    out = tile(f"data/generated/{direction}/images/all/{split}/{cls}/{path.split('/')[-1]}", cls)
                    generated.append(dict(direction=direction, scope="all", split=split, **{"class": cls}, input_path=path,
                                          output_path=out, ground_truth_path=None, model="models/x/all/generator.pt"))
        pd.DataFrame(generated).to_parquet(root / f"data/generated/{direction}/generated.parquet")
    return splits


def classify_params(**overrides):
    return tiny_params(classify=dict(dict(size=32, width=0.125, epochs=2, seeds=[0, 1], batch_size=8,
                                          low_data_fraction=0.34), **overrides))


@pytest.mark.slow
def test_stage_writes_tables_summary_and_plot(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path)
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(classify_params()))
    assert main(["classify", "--params", "params.yaml", "--modality", "tactile", "--pairs", "data/pairs",
                 "--generated", "data/generated", "--out", "out/tactile"]) == 0
    out = tmp_path / "out/tactile"
    table = pd.read_parquet(out / "accuracy.parquet")
    assert list(table.columns) == list(ACCURACY_COLUMNS)
    confident = "real+generated (confident, ratio 0.5)"  # the policy's second default candidate; the first is real+generated
    assert set(table["setting"]) == set(SETTINGS) | {confident}
    assert len(table) == (len(SETTINGS) + 1) * 2 * 2 and len(pd.read_csv(out / "accuracy.csv")) == len(table)
    assert table["val_accuracy"].between(0, 1).all()  # one validation image per class
    assert sorted(table["epoch"].unique()) == [1, 2] and (table["modality"] == "tactile").all()
    counts = table.groupby("setting")[["train_images", "real_images", "generated_images"]].first()
    assert counts.loc["real"].tolist() == [18, 18, 0]
    assert counts.loc["real+generated"].tolist() == [27, 18, 9]
    assert counts.loc["low-data real"].tolist() == [6, 6, 0]  # round(0.34 * 6) = 2 per class
    assert counts.loc["low-data real+generated"].tolist() == [15, 6, 9]
    repeats = json.loads((out / "summary.json").read_text())["counts"]["real_repeats"]  # classify.real_share 0.5
    assert repeats["real+generated"] == {"0": 1, "1": 1}  # 18 real beside 9 generated: already the larger share
    assert repeats["low-data real+generated"] == {"0": 2, "1": 2}  # 6 real visited twice beside 9 generated
    real = table["setting"] == "real"
    assert table.loc[real, "gan_test_accuracy"].notna().all() and table.loc[~real, "gan_test_accuracy"].isna().all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "ok" and summary["classes"] == list(CLASSES) and summary["direction"] == "v2t"
    assert summary["counts"]["generated_test"] == 6 and summary["counts"]["low_data_real_train"] == {"0": 6, "1": 6}
    assert set(summary["settings"]) == set(SETTINGS) | {confident} and len(summary["settings"]["real"]["epoch_mean"]) == 2
    policy = summary["policy"]
    assert policy["val_images"] == 3 and [c["setting"] for c in policy["candidates"]] == ["real+generated", confident]
    assert policy["test"]["setting"] == policy["chosen"] and policy["test"]["images"] == 6
    assert policy["test"]["accuracy"] == summary["settings"][policy["chosen"]]["final_mean"]
    assert 0 <= summary["gan_test"]["final_mean"] <= 1
    assert (out / "curves.png").stat().st_size > 0
    # n and a 95% Wilson interval per class and setting; comparisons are ranked only outside the noise
    by_class = pd.read_csv(out / "by_class.csv", keep_default_na=False)
    assert set(by_class["setting"]) == set(SETTINGS) | {confident, "GAN-test"}
    assert (by_class.loc[by_class["class"] != "(all)", "images"] == 2).all()  # 2 test images per class
    assert (by_class.loc[by_class["class"] == "(all)", "images"] == 6).all()
    assert ((by_class["low"] <= by_class["accuracy"]) & (by_class["accuracy"] <= by_class["high"])).all()
    overall = by_class[(by_class["class"] == "(all)") & (by_class["setting"] == "real")].iloc[0]
    assert overall["accuracy"] == pytest.approx(summary["settings"]["real"]["final_mean"])
    assert summary["settings"]["real"]["interval"] == pytest.approx(list(wilson_interval(overall["accuracy"], 6)), abs=1e-6)
    # the real-only confusion: rows are the 2 test images of each class, its diagonal the real accuracy
    confusion = np.array(summary["real_confusion"])
    assert confusion.shape == (3, 3) and confusion.sum(axis=1) == pytest.approx([2, 2, 2])
    assert np.trace(confusion) / 6 == pytest.approx(summary["settings"]["real"]["final_mean"], abs=1e-6)
    assert [c["setting"] for c in summary["comparisons"]] == ["real+generated", "low-data real+generated"]
    for item in summary["comparisons"]:  # ranked by the paired interval over the shared test images
        low, high = item["paired_interval"]
        assert low <= item["difference"] <= high and item["within_noise"] == (low <= 0 <= high)
        assert item["within_noise"] == item["verdict"].startswith("within noise (the paired 95% interval includes 0)")
    # all real training images against the low-data share, paired the same way
    more = summary["more_real_data"]
    assert (more["setting"], more["against"]) == ("real", "low-data real")
    assert more["difference"] == pytest.approx(summary["settings"]["real"]["final_mean"]
                                               - summary["settings"]["low-data real"]["final_mean"], abs=1e-6)
    assert more["paired_interval"][0] <= more["difference"] <= more["paired_interval"][1]
    assert summary["test_images_per_class"] == {c: 2 for c in CLASSES}
    # images per second: every image visit of every setting, seed and epoch, and every image evaluated
    speed = summary["throughput"]
    runs = table.groupby(["setting", "seed"]).ngroup().nunique() - (table["seconds"] == 0).sum() // 2  # reused: not run
    assert speed["train_images"] == 2 * 18 * runs  # epoch_images real: each epoch of every run is 18 visits, real's set
    assert speed["eval_images"] == 2 * (runs * (6 + 3) + 2 * 6)  # epochs x (test + validation per run, GAN-test)
    for kind in ("train", "eval"):
        assert speed[f"{kind}_seconds"] > 0
        assert speed[f"{kind}_images_per_second"] == pytest.approx(speed[f"{kind}_images"] / speed[f"{kind}_seconds"],
                                                                   rel=0.02)
    # the real-only classifier of the first seed is kept as the score stage's feature encoder
    from vtgen.core.classifier import predict
    from vtgen.io.classifiers import load_classifier
    from vtgen.io.images import read_tiles

    encoder, record = load_classifier(out / "encoder.pt")
    assert record["classes"] == list(CLASSES) and record["seed"] == 0 and record["modality"] == "tactile"
    real = pd.read_parquet(tmp_path / "data/pairs/splits.parquet")
    test = real[(real["modality"] == "tactile") & (real["split"] == "test")].sort_values("path")
    labels = np.array([CLASSES.index(c) for c in test["class"]])
    seed0 = table[(table["setting"] == "real") & (table["seed"] == 0) & (table["epoch"] == 2)]["test_accuracy"].iloc[0]
    assert (predict(encoder, read_tiles(list(test["path"]), 32)).numpy() == labels).mean() == pytest.approx(seed0)


def test_real_repeats_keep_the_real_share_of_visits():
    from vtgen.stages.classify import real_repeats

    assert real_repeats(52, 516, 0.5) == 10  # 520 real visits beside 516 generated
    assert real_repeats(52, 520, 0.5) == 10 and real_repeats(52, 521, 0.5) == 11  # at least the share
    assert real_repeats(516, 516, 0.5) == 1 and real_repeats(516, 100, 0.5) == 1  # never fewer than one pass
    assert real_repeats(10, 30, 0.75) == 9  # 90 real of 120 visits
    assert real_repeats(52, 516, 0.0) == 1 and real_repeats(52, 0, 0.5) == 1  # share 0 or nothing generated: pooled
    for real, generated, share in ((52, 516, 0.5), (7, 40, 0.3), (3, 100, 0.9)):
        r = real_repeats(real, generated, share)
        assert real * r / (real * r + generated) >= share > real * (r - 1) / (real * (r - 1) + generated)


def test_training_set_repeats_the_real_images_and_share_zero_is_the_pooled_set():
    from vtgen.stages.classify import _training_set

    g = torch.Generator().manual_seed(0)
    sets = {"train": (torch.randint(0, 256, (12, 3, 8, 8), dtype=torch.uint8, generator=g), torch.arange(12) % 3),
            "generated": (torch.randint(0, 256, (9, 3, 8, 8), dtype=torch.uint8, generator=g), torch.arange(9) % 3)}
    subset = torch.tensor([0, 1, 2])
    pooled_x, pooled_y, real, repeats = _training_set("low-data real+generated", 0, sets, subset, {}, None, 0.0)
    assert (real, repeats) == (3, 1)
    assert torch.equal(pooled_x, torch.cat([sets["train"][0][subset], sets["generated"][0]]))  # today's set, bit for bit
    assert torch.equal(pooled_y, torch.cat([sets["train"][1][subset], sets["generated"][1]]))
    x, y, real, repeats = _training_set("low-data real+generated", 0, sets, subset, {}, None, 0.5)
    assert (real, repeats, len(x)) == (3, 3, 18)  # 9 real visits beside 9 generated
    assert torch.equal(x[:9], sets["train"][0][subset].repeat(3, 1, 1, 1)) and torch.equal(x[9:], sets["generated"][0])
    assert torch.equal(y, torch.cat([sets["train"][1][subset].repeat(3), sets["generated"][1]]))
    x, _, real, repeats = _training_set("low-data real", 0, sets, subset, {}, None, 0.5)  # no generated: no repeat
    assert (real, repeats, len(x)) == (3, 1, 3)


def test_stage_refuses_a_generated_training_image_from_a_test_input(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    splits = fake_layout(tmp_path)
    table_path = tmp_path / "data/generated/t2v/generated.parquet"
    table = pd.read_parquet(table_path)
    test_tile = splits[(splits["modality"] == "tactile") & (splits["split"] == "test")]["path"].iloc[0]
    table.loc[table.index[table["split"] == "train"][0], "input_path"] = test_tile
    table.to_parquet(table_path)
    with pytest.raises(ValueError, match="split leak: 1 generated 'train' image"):
        run_classify(classify_params(), "visual", "data/pairs", "data/generated", "out/visual", progress=False)
    assert not (tmp_path / "out/visual").exists()


def test_stage_without_generated_training_images_skips_those_settings_and_uses_weights(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path, generated_train=0)
    torch.save(make_classifier(7, TINY, 0).state_dict(), tmp_path / "start.pt")
    params = classify_params(seeds=[0], epochs=1, weights="start.pt", retrain_layers=1)
    summary = run_classify(params, "visual", "data/pairs", "data/generated", "out/visual", progress=False)
    table = pd.read_parquet(tmp_path / "out/visual/accuracy.parquet")
    assert sorted(table["setting"].unique()) == ["low-data real", "real"]
    assert set(summary["skipped"]) == {"real+generated", "low-data real+generated"}
    assert summary["weights"] == "start.pt"
    params["classify"]["weights"] = "missing.pt"
    with pytest.raises(ValueError, match="missing.pt: weights file not found"):
        run_classify(params, "visual", "data/pairs", "data/generated", "out/visual", progress=False)


def test_stage_with_one_class_reports_not_applicable(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path, classes=("felt",))
    summary = run_classify(classify_params(), "visual", "data/pairs", "data/generated", "out/visual", progress=False)
    assert summary["status"] == "not applicable: classification needs at least 2 classes, the data has 1 (felt)"
    table = pd.read_parquet(tmp_path / "out/visual/accuracy.parquet")
    assert table.empty and list(table.columns) == list(ACCURACY_COLUMNS)
    assert json.loads((tmp_path / "out/visual/summary.json").read_text())["status"] == summary["status"]
    assert "warning" in capsys.readouterr().out
    assert (tmp_path / "out/visual/curves.png").is_file()


def test_wilson_interval_and_the_at_chance_rule():
    low, high = wilson_interval(0.5, 100)
    assert low == pytest.approx(0.4038, abs=1e-4) and high == pytest.approx(0.5962, abs=1e-4)
    assert wilson_interval(0.0, 10)[0] == 0.0 and 0.27 < wilson_interval(0.0, 10)[1] < 0.28
    assert at_chance(0.09, 120, 12)  # the 12-class paper layout: 0.09 on 120 images is chance (1/12)
    assert not at_chance(0.5, 120, 12)
    assert at_chance(0.5, 6, 3) and not at_chance(1.0, 6, 3)  # 6 images cannot tell 0.5 from 1/3; 1.0 they can
    assert not at_chance(0.0, 200, 3)  # far below chance is distinguishable from chance (it is worse)
    assert not at_chance(float("nan"), 0, 3) and not at_chance(0.3, 0, 3)  # nothing measured: nothing flagged


def test_confusion_counts_average_the_runs():
    labels = np.array([0, 0, 1, 1])
    matrix = confusion_counts([np.array([0, 1, 1, 1]), np.array([0, 0, 0, 1])], labels, 2)
    assert matrix.tolist() == [[1.5, 0.5], [0.5, 1.5]]


def test_realistic_gan_test_replaces_each_input_by_a_real_image_of_the_class_read_or_told():
    judge = np.array([[8.0, 2.0], [4.0, 6.0]])  # real targets: class 0 called 0 at 0.8, class 1 called 1 at 0.6
    perfect_reader = np.diag([5.0, 5.0])
    assert realistic_gan_test(perfect_reader, judge, told_class=False) == pytest.approx(0.7)
    # a reader that calls every input class 0: each becomes a class-0 image, called 0 at 0.8 and 1 at 0.2
    blind = np.array([[5.0, 0.0], [5.0, 0.0]])
    assert realistic_gan_test(blind, judge, told_class=False) == pytest.approx((5 * 0.8 + 5 * 0.2) / 10)
    # told the class, the reader's mistakes do not matter: the judge's accuracy weighted by the inputs' classes
    assert realistic_gan_test(blind, judge, told_class=True) == pytest.approx(0.7)
    skewed = np.array([[9.0, 0.0], [1.0, 0.0]])
    assert realistic_gan_test(skewed, judge, told_class=True) == pytest.approx((9 * 0.8 + 1 * 0.6) / 10)
    # a reader that swaps the two classes: each input becomes a real image of the other class
    swapped = np.array([[0.0, 5.0], [5.0, 0.0]])
    assert realistic_gan_test(swapped, judge, told_class=False) == pytest.approx((5 * 0.4 + 5 * 0.2) / 10)
    # no real target of a class that is needed, shapes that differ, nothing read: no number
    assert realistic_gan_test(blind, np.array([[0.0, 0.0], [4.0, 6.0]]), told_class=False) is None
    assert realistic_gan_test(np.diag([1.0, 1.0, 1.0]), judge, told_class=False) is None
    assert realistic_gan_test(np.zeros((2, 2)), judge, told_class=False) is None


def test_non_finite_training_loss_stops_naming_the_epoch_and_seed():
    x, y = stripes(10, seed=0)  # two batches: the second starts from NaN weights
    with pytest.raises(TrainingDiverged, match=r"mean loss nan in epoch 1 \(seed 5\); lower classify.lr") as caught:
        train_classifier(x, y, x, y, 3, dict(TINY, lr=1e12), seed=5)
    assert caught.value.epoch == 1 and caught.value.seed == 5 and isinstance(caught.value, RuntimeError)


def run_stage_cli(tmp_path, params, capsys, modality="visual"):
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    code = main(["classify", "--params", "params.yaml", "--modality", modality, "--pairs", "data/pairs",
                 "--generated", "data/generated", "--out", f"out/{modality}"])
    return code, capsys.readouterr()


@pytest.mark.slow
def test_stage_on_separable_data_is_not_flagged(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path, test=6)  # 18 test images of three colour-coded classes
    # 4 epochs: under the default cosine schedule the third epoch of 3 runs at a quarter of the rate, and one run of
    # ten read 12 of 18 there
    code, printed = run_stage_cli(tmp_path, classify_params(epochs=4), capsys)
    assert code == 0, printed.err
    table = pd.read_parquet(tmp_path / "out/visual/accuracy.parquet")
    final = table[table["epoch"] == 4]
    assert (final["test_accuracy"] > 0.8).all() and not final["at_chance"].any()
    assert table["at_chance"].dtype == bool
    summary = json.loads((tmp_path / "out/visual/summary.json").read_text())
    assert summary["chance"] == pytest.approx(1 / 3)
    assert set(SETTINGS) <= set(summary["settings"])  # and the policy's candidates
    assert not any(s["at_chance"] for s in summary["settings"].values())
    assert summary["gan_test"]["at_chance"] is False and summary["gan_test"]["images"] == 18
    assert "chance level" not in printed.out + printed.err


@pytest.mark.slow
def test_stage_at_an_absurd_learning_rate_is_flagged_or_stopped(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path, test=6)
    params = classify_params(lr=1e6, seeds=[0])
    code, printed = run_stage_cli(tmp_path, params, capsys)
    out = tmp_path / "out/visual"
    if code != 0:  # the loss overflowed: one line naming where, no outputs
        assert code == 2 and not out.exists()
        assert printed.err.count("\n") == 1 and "vtgen classify: error: classify visual: setting '" in printed.err
        assert "seed 0: the training loss became non-finite" in printed.err and "lower classify.lr" in printed.err
        return
    summary = json.loads((out / "summary.json").read_text())
    flagged = [name for name, s in summary["settings"].items() if s["at_chance"]]
    assert "real" in flagged
    table = pd.read_parquet(out / "accuracy.parquet")
    assert table[(table["setting"] == "real") & (table["epoch"] == 2)]["at_chance"].all()
    warnings = [line for line in printed.out.splitlines() if "ended at chance level" in line]
    assert len(warnings) == len(flagged) + summary["gan_test"]["at_chance"]
    assert (f"classify visual: warning: 'real' ended at chance level (accuracy {summary['settings']['real']['final_mean']:.2f} "
            f"on 18 test images, chance 0.33); check classify.lr (1e+06)") in printed.out


@pytest.mark.parametrize("threads", [1, 2])
def test_stage_stops_when_the_training_loss_becomes_non_finite(tmp_path, monkeypatch, threads):
    """In one process, or with the seeds in worker processes (whose first error stops the rest)."""
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path)
    params = classify_params(lr=1e12, seeds=[0, 1, 2, 3], threads=threads)
    with pytest.raises(RuntimeError, match=r"^classify tactile: setting 'real', seed 0: the training loss became "
                                           r"non-finite \(nan\) in epoch 1; lower classify.lr \(now 1e\+12\)$"):
        run_classify(params, "tactile", "data/pairs", "data/generated", "out/tactile", progress=False)
    assert not (tmp_path / "out/tactile").exists()


def truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])


def test_read_tiles_names_a_truncated_or_corrupt_tile_and_the_remedy(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("good.png", "cut.png", "junk.png"):
        write_image(tmp_path / name, rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
    truncate(tmp_path / "cut.png")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(200))
    write_image(tmp_path / "big.png", rng.integers(0, 256, (48, 48, 3), dtype=np.uint8))
    assert read_tiles(["good.png"], 32, tmp_path).shape == (1, 3, 32, 32)
    with pytest.raises(ValueError, match=r"^.*/cut\.png: truncated tile \(image file is truncated.*\); rerun the roi stage$"):
        read_tiles(["good.png", "cut.png"], 32, tmp_path)
    with pytest.raises(ValueError, match=r"junk\.png: .*; rerun the roi stage$"):
        read_tiles(["junk.png"], 32, tmp_path)
    with pytest.raises(ValueError, match=r"gone\.png: tile not found \(no such file\); rerun the generate stage$"):
        read_tiles(["gone.png"], 32, tmp_path, remedy="rerun the generate stage")
    with pytest.raises(ValueError, match=r"big\.png: tile is 48x48, but .*good\.png is 32x32; rerun the roi stage"):
        read_tiles(["good.png", "big.png"], 32, tmp_path)


def test_stage_names_a_truncated_tile_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path)
    truncate(tmp_path / "data/roi/visual/felt/train3.png")
    code, printed = run_stage_cli(tmp_path, classify_params(), capsys)
    assert code == 2 and printed.err.count("\n") == 1, printed.err  # one line, no traceback
    assert printed.err.startswith("vtgen classify: error: data/roi/visual/felt/train3.png: truncated tile (image file is")
    assert printed.err.endswith("; rerun the roi stage\n")
    generated = tmp_path / "data/generated/t2v/images/all/train/denim/train0.png"
    generated.write_bytes(b"not an image")
    write_image(tmp_path / "data/roi/visual/felt/train3.png", np.zeros((32, 32, 3), dtype=np.uint8))  # repaired
    code, printed = run_stage_cli(tmp_path, classify_params(), capsys)
    assert code == 2 and "train/denim/train0.png: not a decodable image; rerun the generate stage (t2v)" in printed.err


def test_wilson_interval_always_holds_the_observed_share():
    for count in (1, 3, 7, 144, 10_000):
        for accuracy in (0.0, 1.0, 1 / 3):
            low, high = wilson_interval(accuracy, count)
            assert 0.0 <= low <= accuracy <= high <= 1.0
    assert wilson_interval(1.0, 144)[1] == 1.0 and wilson_interval(0.0, 144)[0] == 0.0
    assert wilson_interval(0.5, 0) == (0.0, 1.0)


# ---------------------------------------------------------------- the policy: which generated images the default adds


def noise_layout(root, train=6, val=3, test=4, noise_per_input=4, spread=30):
    """Real tactile and visual tiles of three colour classes with pixel noise (learnt within a few epochs), and
    generated training images that are PURE NOISE (uniform random pixels, labelled with their input's class),
    ``noise_per_input`` per real training input, so that they outnumber the real training images."""
    rng = np.random.default_rng(1)
    rows, generated = [], []
    centre = {"denim": (90, 110, 160), "felt": (160, 90, 90), "satin": (120, 160, 110)}

    def tile(path, cls=None):
        pixels = (rng.integers(0, 256, (32, 32, 3)) if cls is None
                  else np.clip(np.array(centre[cls]) + rng.normal(0, spread, (32, 32, 3)), 0, 255))
        write_image(root / path, pixels.astype(np.uint8))
        return path

    for cls in CLASSES:
        for modality in ("visual", "tactile"):
            for split, count in (("train", train), ("val", val), ("test", test)):
                for i in range(count):
                    rows.append(dict(path=tile(f"data/roi/{modality}/{cls}/{split}{i}.png", cls), **{"class": cls},
                                     modality=modality, source=f"{cls}-{split}{i}", group=f"{cls}-{split}{i}",
                                     split=split))
    splits = pd.DataFrame(rows)
    (root / "data/pairs").mkdir(parents=True)
    splits.to_parquet(root / "data/pairs/splits.parquet")
    for direction, source in (("v2t", "visual"), ("t2v", "tactile")):
        generated = []
        for row in splits[(splits["modality"] == source) & (splits["split"] == "train")].itertuples():
            for k in range(noise_per_input):
                out = tile(f"data/generated/{direction}/{row.source}_{k}.png")
                generated.append(dict(direction=direction, scope="all", split="train", **{"class": row[2]},
                                      input_path=row.path, output_path=out, ground_truth_path=None, model="noise"))
        pd.DataFrame(generated).to_parquet(root / f"data/generated/{direction}/generated.parquet")
    return splits


@pytest.mark.slow
def test_policy_adds_no_pure_noise_and_reports_the_real_only_accuracy(tmp_path, monkeypatch):
    """Generated images that are pure noise: the policy keeps real only, and the accuracy it reports is the
    real-only one. The noise does lower the accuracy of a classifier that adds it (checked below), so a
    policy that added it, or a report that read another setting, would fail here."""
    monkeypatch.chdir(tmp_path)
    noise_layout(tmp_path)
    params = classify_params(epochs=4, seeds=[0, 1], patience=0,
                             policy={"mode": "auto", "confidence": 0.5,
                                     "candidates": [{"ratio": 4.0, "filter": "all"}, {"ratio": 0.5, "filter": "confident"}]})
    summary = run_classify(params, "tactile", "data/pairs", "data/generated", "out/tactile", progress=False)
    policy, settings = summary["policy"], summary["settings"]
    assert policy["chosen"] == "real" and policy["uses_generated"] is False
    assert "no candidate beat real only" in policy["reason"]
    assert policy["test"]["accuracy"] == settings["real"]["final_mean"] == policy["test"]["real_accuracy"]
    assert policy["test"]["interval"] == settings["real"]["interval"] and policy["test"]["gain"] == 0
    # the candidates were real: four noise images per real one were added, and they cost accuracy
    candidates = {c["setting"]: c for c in policy["candidates"]}
    assert candidates["real+generated"]["generated_images"] == [72, 72]
    assert candidates["real+generated"]["val_gain"] < 0
    assert settings["real+generated"]["final_mean"] < settings["real"]["final_mean"]
    metrics_policy = json.loads((tmp_path / "out/tactile/summary.json").read_text())["policy"]
    assert metrics_policy["chosen"] == "real"


@pytest.mark.slow
def test_the_gan_test_of_outputs_told_the_class_read_is_the_real_only_accuracy_on_them(tmp_path, monkeypatch):
    """Generated rows of split test_read (test inputs told the class read from them) are scored by the real-only
    classifiers against their input's class: where those images are the real test images themselves, the score is
    the real-only test accuracy to the digit, with its n and interval; without such rows the summary has no
    ``gan_test_read``; a test_read row made from a training input is refused as a split leak."""
    monkeypatch.chdir(tmp_path)
    splits = noise_layout(tmp_path, val=0, noise_per_input=1)
    table_path = tmp_path / "data/generated/t2v/generated.parquet"
    generated = pd.read_parquet(table_path)
    inputs = splits[(splits["modality"] == "tactile") & (splits["split"] == "test")].sort_values("path")
    targets = splits[(splits["modality"] == "visual") & (splits["split"] == "test")].sort_values("path")
    read = pd.DataFrame(dict(direction="t2v", scope="all", split="test_read", **{"class": list(targets["class"])},
                             input_path=list(inputs["path"]), output_path=list(targets["path"]),
                             ground_truth_path=None, model="copies"))
    assert list(inputs["class"]) == list(targets["class"])
    pd.concat([generated, read], ignore_index=True).to_parquet(table_path)
    params = classify_params(epochs=2, seeds=[0, 1])
    summary = run_classify(params, "visual", "data/pairs", "data/generated", "out/visual", progress=False)
    told_read, real = summary["gan_test_read"], summary["settings"]["real"]
    assert told_read["final_mean"] == real["final_mean"] and told_read["images"] == len(targets) == 12
    assert told_read["seeds"] == 2 and told_read["interval"] == real["interval"]
    plain = run_classify(params, "tactile", "data/pairs", "data/generated", "out/tactile", progress=False)
    assert "gan_test_read" not in plain
    leaked = read.assign(input_path=list(splits[(splits["modality"] == "tactile")
                                                & (splits["split"] == "train")]["path"][:12]))
    pd.concat([generated, leaked], ignore_index=True).to_parquet(table_path)
    with pytest.raises(ValueError, match="'test_read' image.*not test-split tactile tiles"):
        run_classify(params, "visual", "data/pairs", "data/generated", "out/visual2", progress=False)


@pytest.mark.slow
def test_policy_without_a_validation_split_is_real_only_and_says_why(tmp_path, monkeypatch):
    """Too few groups for a validation split: no candidate is trained and the reason is recorded."""
    monkeypatch.chdir(tmp_path)
    noise_layout(tmp_path, val=0, noise_per_input=1)
    summary = run_classify(classify_params(epochs=1, seeds=[0]), "visual", "data/pairs", "data/generated", "out/visual",
                           progress=False)
    policy = summary["policy"]
    assert policy["chosen"] == "real" and policy["candidates"] == [] and policy["val_images"] == 0
    assert "3 of 3 classes have no validation images" in policy["reason"] and "too few groups" in policy["reason"]
    assert set(summary["settings"]) == set(SETTINGS)  # no candidate setting was trained
    assert policy["test"]["accuracy"] == summary["settings"]["real"]["final_mean"]


@pytest.mark.slow
@pytest.mark.parametrize("class_pairs_only, expected", [(True, [0, 1]), (False, [0]), (None, [0])])
def test_seeds_follow_the_kind_of_pairs(tmp_path, monkeypatch, class_pairs_only, expected):
    """classify.seeds as a mapping: the class_pairs list where the pairs summary says every training pair is a
    class pair, the paired list where it does not or where there is no summary; summary.json says which and why."""
    monkeypatch.chdir(tmp_path)
    noise_layout(tmp_path, val=0, noise_per_input=1)
    if class_pairs_only is not None:
        (tmp_path / "data/pairs/summary.json").write_text(json.dumps({"data_kind": {"class_pairs_only": class_pairs_only}}))
    params = classify_params(epochs=1, seeds={"paired": [0], "class_pairs": [0, 1]})
    summary = run_classify(params, "visual", "data/pairs", "data/generated", "out/visual", progress=False)
    table = pd.read_parquet(tmp_path / "out/visual/accuracy.parquet")
    assert sorted(table["seed"].unique()) == expected and summary["seeds"]["seeds"] == expected
    assert summary["settings"]["real"]["seeds"] == len(expected)
    why = {True: "every training pair is a class pair", False: "some training pairs are pixel or name pairs",
           None: "no pairs summary"}[class_pairs_only]
    assert why in summary["seeds"]["why"]


@pytest.mark.slow
def test_seeds_in_worker_processes_give_the_results_of_one_process(tmp_path, monkeypatch):
    """classify.threads 2 trains the seeds in two single-threaded processes: the accuracy table (seconds aside), the
    counts, the policy and the encoder are those of the one-process run; classify.threads 1 is that run."""
    monkeypatch.chdir(tmp_path)
    fake_layout(tmp_path)
    outputs = {}
    for threads in (1, 2):
        params = classify_params(seeds=[0, 1, 2], threads=threads)
        summary = run_classify(params, "tactile", "data/pairs", "data/generated", f"out/{threads}", progress=False)
        table = pd.read_parquet(tmp_path / f"out/{threads}/accuracy.parquet").drop(columns="seconds")
        encoder = torch.load(tmp_path / f"out/{threads}/encoder.pt", weights_only=True)["state_dict"]
        outputs[threads] = (table, summary, encoder)
    (one, one_summary, one_encoder), (two, two_summary, two_encoder) = outputs[1], outputs[2]
    pd.testing.assert_frame_equal(one, two)
    assert len(one) == (len(SETTINGS) + 1) * 3 * 2  # three seeds ran, each with every setting
    for key in ("counts", "settings", "comparisons", "policy", "gan_test", "real_confusion"):
        assert one_summary[key] == two_summary[key], key
    assert one_summary["throughput"]["train_images"] == two_summary["throughput"]["train_images"]
    assert one_encoder.keys() == two_encoder.keys()
    assert all(torch.equal(one_encoder[name], two_encoder[name]) for name in one_encoder)


def test_paired_difference_counts_groups_not_images():
    from vtgen.core.generated_policy import paired_difference

    better = np.array([1, 1, 1, 1, 0, 0, 1, 1])
    base = np.array([0, 0, 0, 0, 0, 0, 1, 1])
    gain, low, high = paired_difference(better, base, np.arange(8))
    assert gain == pytest.approx(0.5) and low < 0.5 < high
    # one seed: the per-image part alone, sqrt(8/7 * sum((d - 0.5)^2)) / 8 with d four 1s and four 0s
    assert (high - low) / 2 == pytest.approx(1.959964 * np.sqrt(8 / 7 * 8 * 0.25) / 8, rel=1e-5)
    # the same images in two groups of four: half the units, a wider interval around the same gain
    gain2, low2, high2 = paired_difference(better, base, np.repeat([0, 1], 4))
    assert gain2 == pytest.approx(0.5) and high2 - low2 > high - low
    assert paired_difference(base, base, np.arange(8)) == (0.0, 0.0, 0.0)
    # seeds x images: the mean over seeds, and seeds that disagree widen the interval
    two_seeds = paired_difference(np.stack([better, base]), np.stack([base, base]), np.arange(8))
    agreeing = paired_difference(np.stack([better, better]), np.stack([base, base]), np.arange(8))
    assert two_seeds[0] == pytest.approx(0.25) and agreeing[2] - agreeing[1] == pytest.approx(high - low)


def test_choose_takes_a_candidate_only_beyond_its_interval():
    from vtgen.core.generated_policy import choose

    groups = np.arange(40)
    real = np.tile(np.r_[np.ones(20), np.zeros(20)], (2, 1))
    clearly = real.copy()
    clearly[:, 20:36] = 1  # right on 16 of the 20 images real gets wrong, both seeds
    slightly = real.copy()
    slightly[:, 20:22] = 1  # 2 more right: within noise
    result = choose({"real": real, "slight": slightly, "clear": clearly}, groups)
    assert result["chosen"] == "clear" and "beat real only" in result["reason"]
    rows = {r["setting"]: r for r in result["candidates"]}
    assert rows["clear"]["val_gain"] == pytest.approx(0.4) and rows["clear"]["val_gain_interval"][0] > 0
    assert rows["slight"]["val_gain_interval"][0] <= 0
    assert choose({"real": real, "slight": slightly}, groups)["chosen"] == "real"


def test_generated_subset_caps_per_class_and_filters_by_confidence():
    from vtgen.core.generated_policy import generated_subset

    labels = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    probability = np.array([0.9, 0.2, 0.7, 0.6, 0.1, 0.3, 0.95, 0.4])
    assert generated_subset(labels, {0: 4, 1: 4}, 1.0, "all", 0).tolist() == list(range(8))
    capped = generated_subset(labels, {0: 2, 1: 4}, 1.0, "all", 0)
    assert sum(labels[capped] == 0) == 2 and sum(labels[capped] == 1) == 4
    assert capped.tolist() == generated_subset(labels, {0: 2, 1: 4}, 1.0, "all", 0).tolist()  # seeded
    # confident: own-class probability >= 0.5, most confident first, at most ratio x real per class
    assert generated_subset(labels, {0: 4, 1: 4}, 1.0, "confident", 0, probability, 0.5).tolist() == [0, 2, 3, 6]
    assert generated_subset(labels, {0: 2, 1: 2}, 0.5, "confident", 0, probability, 0.5).tolist() == [0, 6]
    with pytest.raises(ValueError, match="unknown generated-image filter"):
        generated_subset(labels, {0: 4}, 1.0, "best", 0)


def test_early_stopping_ends_a_run_on_the_validation_accuracy():
    from vtgen.core.classifier import EarlyStopping

    stop = EarlyStopping(2)
    assert [stop.should_stop(e, v) for e, v in enumerate([0.5, 0.6, 0.6, 0.55], start=1)] == [False, False, False, True]
    assert stop.best_epoch == 2
    assert not any(EarlyStopping(0).should_stop(e, 0.1) for e in range(1, 20))
    # in training: the run ends one epoch (patience 1) after its last new best validation accuracy
    train_x, train_y = stripes(6, seed=0)
    test_x, test_y = stripes(2, seed=1)
    run = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=6, patience=1), seed=0,
                           val=(test_x[:1], test_y[:1]))
    assert len(run.test_accuracy) == len(run.extra_accuracy["val"]) <= 6
    accuracies = run.extra_accuracy["val"]
    best = accuracies.index(max(accuracies)) + 1
    assert len(accuracies) == min(6, best + 1)  # stopped one epoch after the last new best
    assert len(train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=3, patience=1), seed=0)
               .test_accuracy) == 3  # without a validation set, every epoch runs


def test_bf16_precision_trains_and_the_default_is_the_plain_fp32_step():
    train_x, train_y = stripes(6, seed=0)
    test_x, test_y = stripes(2, seed=1)
    settings = dict(TINY, epochs=1)
    fp32 = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=0)
    same = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=0, precision="fp32")
    bf16 = train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=0, precision="bf16")
    assert fp32.train_loss == same.train_loss and np.isfinite(bf16.train_loss).all()
    assert bf16.train_loss != fp32.train_loss  # the forward passes ran in bf16
    with pytest.raises(ValueError, match="precision must be fp32 or bf16"):
        train_classifier(train_x, train_y, test_x, test_y, 3, settings, seed=0, precision="fp16")


def test_weight_averaging_keeps_the_mean_of_the_last_epochs_weights_and_zero_is_todays_run():
    train_x, train_y = stripes(6, seed=0)
    test_x, test_y = stripes(2, seed=1)
    plain = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=3), seed=0)
    explicit = train_classifier(train_x, train_y, test_x, test_y, 3,
                                dict(TINY, epochs=3, average_epochs=0, lr_schedule="constant"), seed=0)
    assert plain.train_loss == explicit.train_loss and plain.test_accuracy == explicit.test_accuracy
    for name, value in plain.model.state_dict().items():
        assert torch.equal(value, explicit.model.state_dict()[name]), name
    # averaging does not change the trajectory: the average of epochs 2 and 3 is the mean of the weights of the
    # runs that stop after epoch 2 and after epoch 3
    two = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=2), seed=0)
    averaged = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=3, average_epochs=2), seed=0)
    assert averaged.train_loss == plain.train_loss
    assert averaged.test_accuracy[0] == plain.test_accuracy[0]  # epoch 1 is before the window
    moved = 0
    for name, weight in averaged.model.named_parameters():
        expected = (dict(two.model.named_parameters())[name] + dict(plain.model.named_parameters())[name]) / 2
        assert torch.allclose(weight, expected, atol=1e-6), name
        moved += not torch.allclose(weight, dict(plain.model.named_parameters())[name])
    assert moved > 0
    with pytest.raises(ValueError, match="average_epochs"):
        train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, average_epochs=-1), seed=0)


@pytest.mark.filterwarnings("ignore:Detected call of")
def test_cosine_schedule_lowers_the_rate_each_epoch_by_the_formula():
    from vtgen.core.classifier import _lr_schedule

    weight = torch.nn.Parameter(torch.zeros(1))
    optimiser = torch.optim.Adam([weight], lr=0.01)
    schedule = _lr_schedule(optimiser, "cosine", 4)
    rates = [optimiser.param_groups[0]["lr"]]
    for _ in range(3):
        schedule.step()
        rates.append(optimiser.param_groups[0]["lr"])
    assert rates == pytest.approx([0.01 * (1 + np.cos(np.pi * e / 4)) / 2 for e in range(4)])
    assert _lr_schedule(optimiser, "constant", 4) is None
    with pytest.raises(ValueError, match="lr_schedule"):
        _lr_schedule(optimiser, "step", 4)
    # in training: a lower rate in the later epochs changes the run
    train_x, train_y = stripes(6, seed=0)
    test_x, test_y = stripes(2, seed=1)
    plain = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=2), seed=0)
    cosine = train_classifier(train_x, train_y, test_x, test_y, 3, dict(TINY, epochs=2, lr_schedule="cosine"), seed=0)
    assert cosine.train_loss[0] == plain.train_loss[0] and cosine.train_loss[1] != plain.train_loss[1]
