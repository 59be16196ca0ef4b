"""Conditioning (class maps, reference image) and precision auto: what a generator is told, and in which
precision it trains."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import TINY_MODEL
from vtgen.core.conditioning import Conditioning, typical_images
from vtgen.core.device import native_bf16, resolve_precision
from vtgen.core.models import UNetGenerator
from vtgen.io.checkpoints import load_translator, save_generator
from vtgen.stages.generate import translate
from vtgen.stages.train import PairData, train_translator

SETTINGS = dict(TINY_MODEL, gan_loss="bce", l1_weight=100.0, optimizer="adam", lr=0.002, betas=[0.5, 0.999],
                noise=False)
RUN = dict(device="cpu", precision="fp32", threads=2, checkpoint_every=10**6, resume=False, log_every=10, seed=0)
COLOURS = {"red_cloth": (200, 40, 40), "blue_cloth": (40, 60, 210)}


def colour_blind_pairs(n_per_class: int = 8, size: int = 32, seed: int = 0) -> PairData:
    """T2V-like pairs: grey textured inputs drawn alike for both classes (touch cannot tell colour); each
    target is its input's texture in its class's colour."""
    rng = np.random.default_rng(seed)
    inputs, targets, classes = [], [], []
    for name, colour in COLOURS.items():
        for _ in range(n_per_class):
            texture = rng.integers(60, 196, (size // 4, size // 4)).repeat(4, 0).repeat(4, 1).astype(np.float64)
            inputs.append(np.repeat(texture[None], 3, axis=0))
            shade = texture / 128.0
            targets.append(np.stack([np.clip(c * shade, 0, 255) for c in colour]))
            classes.append(name)
    as_tensor = lambda a: torch.from_numpy(np.round(np.stack(a)).astype(np.uint8))  # noqa: E731
    x = as_tensor(inputs)
    return PairData(x, as_tensor(targets), classes, torch.ones(len(classes), dtype=torch.bool), x.clone(),
                    {c: torch.tensor([i for i, k in enumerate(classes) if k == c]) for c in COLOURS})


def test_class_maps_are_appended_and_labels_name_unknown_classes():
    conditioning = Conditioning("class", ("a", "b", "c"))
    x = torch.zeros(2, 3, 8, 8)
    out = conditioning.condition(x, conditioning.labels(["c", "a"]))
    assert out.shape == (2, 6, 8, 8) and conditioning.extra_channels == 3
    assert torch.equal(out[0, 3:, 0, 0], torch.tensor([-1.0, -1.0, 1.0]))
    assert torch.equal(out[1, 3:, 5, 7], torch.tensor([1.0, -1.0, -1.0]))
    with pytest.raises(ValueError, match="'d' unknown to this model"):
        conditioning.labels(["a", "d"])
    assert Conditioning().condition(x, torch.zeros(2, dtype=torch.int64)) is x


def test_reference_conditioning_adds_the_class_reference_image():
    refs = torch.stack([torch.full((3, 4, 4), 255, dtype=torch.uint8), torch.zeros(3, 4, 4, dtype=torch.uint8)])
    conditioning = Conditioning("reference", ("white", "black"), refs)
    out = conditioning.condition(torch.zeros(1, 3, 8, 8), conditioning.labels(["black"]))
    assert out.shape == (1, 8, 8, 8) and conditioning.extra_channels == 5
    assert torch.equal(out[0, 5:], torch.full((3, 8, 8), -1.0))  # black reference, resized to 8 px
    with pytest.raises(ValueError, match="K x 3 x S x S"):
        Conditioning("reference", ("white",), refs)


def test_typical_image_is_the_one_nearest_the_median_colour():
    images = torch.stack([torch.full((3, 2, 2), v, dtype=torch.uint8) for v in (10, 100, 110, 250, 50)])
    chosen = typical_images(images, ["a", "a", "a", "a", "b"], ("a", "b"))
    assert chosen[0, 0, 0, 0] in (100, 110) and chosen[1, 0, 0, 0] == 50  # not the outliers 10 or 250


def test_generator_output_changes_with_the_class_given():
    torch.manual_seed(0)
    conditioning = Conditioning("class", ("a", "b"))
    generator = UNetGenerator(32, 8, 4, in_channels=3 + conditioning.extra_channels).eval()
    images = torch.randint(0, 256, (1, 3, 32, 32), dtype=torch.uint8).repeat(2, 1, 1, 1)
    out = translate(generator, images, conditioning=conditioning, labels=conditioning.labels(["a", "b"]))
    assert not torch.equal(out[0], out[1])
    with pytest.raises(ValueError, match="one class per image"):
        translate(generator, images, conditioning=conditioning)


@pytest.mark.slow
def test_class_conditioned_t2v_reproduces_each_class_colour(tmp_path):
    """The input cannot tell the colour; told the class, the generator gives each class its colour (within 25
    grey levels per channel), and the model file carries the conditioning to generation."""
    data = colour_blind_pairs()
    names = tuple(sorted(COLOURS))
    conditioning = Conditioning("class", names)
    result = train_translator(data, dict(SETTINGS, iterations=300, batch_size=4), RUN, "t2v", "all",
                              progress=False, conditioning=conditioning)
    save_generator(tmp_path / "generator.pt", result.generator, dict(SETTINGS, iterations=300), "t2v", "all",
                   conditioning=conditioning)
    generator, meta = load_translator(tmp_path)
    assert meta["conditioning"].kind == "class" and meta["conditioning"].classes == names
    test = colour_blind_pairs(n_per_class=4, seed=1)
    out = translate(generator, test.inputs, conditioning=meta["conditioning"],
                    labels=meta["conditioning"].labels(test.classes))
    for name in COLOURS:
        rows = [i for i, c in enumerate(test.classes) if c == name]
        made = out[rows].double().mean(dim=(0, 2, 3))
        wanted = test.targets[rows].double().mean(dim=(0, 2, 3))
        assert (made - wanted).abs().max() < 25, (name, made.tolist(), wanted.tolist())


def test_precision_auto_follows_the_hardware():
    cpu = torch.device("cpu")
    assert resolve_precision("auto", cpu, flags={"avx2", "avx512_bf16"})[0] == "bf16"
    assert resolve_precision("auto", cpu, flags={"avx2", "amx_bf16", "amx_tile"})[0] == "bf16"
    precision, why = resolve_precision("auto", cpu, flags={"avx2", "avx512f"})
    assert precision == "fp32" and "lacks" in why
    assert resolve_precision("fp32", cpu, flags={"avx512_bf16"}) == ("fp32", "as set")
    precision, why = resolve_precision("bf16", cpu, flags=set())
    assert precision == "bf16" and "warning" in why
    with pytest.raises(ValueError, match="unknown precision"):
        resolve_precision("fp16", cpu)


def test_precision_auto_on_cuda_asks_torch_without_emulation(monkeypatch):
    asked = {}

    def supported(including_emulation=True):
        asked["emulation"] = including_emulation
        return True

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", supported)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "Test GPU")
    assert native_bf16(torch.device("cuda"))[0] is True and asked["emulation"] is False
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: False)
    assert resolve_precision("auto", torch.device("cuda"))[0] == "fp32"


def test_training_records_the_precision_it_chose():
    data = colour_blind_pairs(n_per_class=2)
    result = train_translator(data, dict(SETTINGS, iterations=2, batch_size=2), dict(RUN, precision="auto"), "t2v",
                              "all", progress=False)
    expected, _ = resolve_precision("auto", torch.device("cpu"))
    assert result.precision == expected and result.precision_reason.startswith("auto: ")


def test_translate_files_needs_the_class_for_a_class_conditioned_model(tmp_path):
    from PIL import Image

    from vtgen.stages.generate import translate_files

    conditioning = Conditioning("class", ("a", "b"))
    generator = UNetGenerator(32, 4, 4, in_channels=3 + conditioning.extra_channels)
    (tmp_path / "model").mkdir()
    (tmp_path / "in").mkdir()
    save_generator(tmp_path / "model" / "generator.pt", generator, dict(TINY_MODEL, ngf=4), "t2v", "all",
                   conditioning=conditioning)
    Image.fromarray(np.full((32, 32, 3), 90, dtype=np.uint8)).save(tmp_path / "in" / "x.png")
    with pytest.raises(ValueError, match="--class"):
        translate_files(tmp_path / "model", [tmp_path / "in"], tmp_path / "out", as_tiles=True)
    with pytest.raises(ValueError, match="'c' unknown to this model"):
        translate_files(tmp_path / "model", [tmp_path / "in"], tmp_path / "out", as_tiles=True, class_name="c")
    written = translate_files(tmp_path / "model", [tmp_path / "in"], tmp_path / "out", as_tiles=True, class_name="b")
    assert [p.name for p in written] == ["x.png"]


def test_inferred_conditioning_reads_the_class_from_the_input_and_survives_the_model_file(tmp_path):
    """V2T-like pairs where the photo's colour tells the class: translating, the inferred maps of a red input
    are the one-hot maps of red (the classifier's most probable class), whatever label the caller has; training
    (labels given) maps the labels as `class` does; the model file rebuilds the same classifier, and
    `vtgen translate` needs no --class for such a model."""
    import pandas as pd
    from PIL import Image

    from vtgen.stages.generate import translate_files
    from vtgen.stages.train import build_conditioning

    touch_like = colour_blind_pairs()
    data = PairData(touch_like.targets, touch_like.inputs, touch_like.classes, touch_like.aligned,
                    touch_like.targets.clone(), touch_like.input_pool)  # inputs are the coloured images
    pairs = pd.DataFrame({"split": "train", "class": data.classes})
    classify = {"width": 0.25, "epochs": 4, "batch_size": 8, "lr": 0.001}
    conditioning = build_conditioning("inferred", pairs, "all", data, classify, seed=0)
    assert conditioning.classes == ("blue_cloth", "red_cloth") and conditioning.extra_channels == 2
    assert not conditioning.needs_labels
    x = data.inputs.float() / 127.5 - 1
    maps = conditioning.condition(x, None)[:, 3:, 0, 0]
    truth = torch.tensor([conditioning.classes.index(c) for c in data.classes])
    assert torch.equal(maps, F.one_hot(truth, 2).float() * 2 - 1)  # exactly the one-hot maps of the class read
    wrong = 1 - truth
    told = conditioning.condition(x, wrong)[:, 3:, 0, 0]
    assert torch.equal(told, F.one_hot(wrong, 2).float() * 2 - 1)  # training: the labels, as `class`
    probe = UNetGenerator(32, 4, 4, in_channels=3 + conditioning.extra_channels).eval()
    inputs = data.inputs[:6]
    assert torch.equal(translate(probe, inputs, conditioning=conditioning, labels=wrong[:6]),
                       translate(probe, inputs, conditioning=conditioning))  # translating never reads a label

    generator = UNetGenerator(32, 4, 4, in_channels=3 + conditioning.extra_channels)
    (tmp_path / "model").mkdir()
    save_generator(tmp_path / "model" / "generator.pt", generator, dict(TINY_MODEL, ngf=4), "v2t", "all",
                   conditioning=conditioning)
    _, meta = load_translator(tmp_path / "model")
    assert meta["conditioning"].kind == "inferred"
    assert torch.equal(meta["conditioning"].condition(x, None), conditioning.condition(x, None))
    (tmp_path / "in").mkdir()
    Image.fromarray(np.full((32, 32, 3), (200, 40, 40), dtype=np.uint8)).save(tmp_path / "in" / "red.png")
    written = translate_files(tmp_path / "model", [tmp_path / "in"], tmp_path / "out", as_tiles=True)
    assert [p.name for p in written] == ["red.png"]
    with pytest.raises(ValueError, match="needs the classify settings"):
        build_conditioning("inferred", pairs, "all", data)


def test_inferred_epochs_sets_how_long_the_input_classifier_trains(monkeypatch):
    """``translation.inferred_epochs`` replaces classify's epochs for the input classifier (and nothing else of
    classify's settings); None keeps classify's."""
    import pandas as pd

    import vtgen.stages.train as train_module

    seen = []
    real_train = train_module.train_classifier

    def recording(images, labels, test_images, test_labels, num_classes, settings, seed, **kwargs):
        run = real_train(images, labels, test_images, test_labels, num_classes, settings, seed, **kwargs)
        seen.append((dict(settings), len(run.test_accuracy)))
        return run

    monkeypatch.setattr(train_module, "train_classifier", recording)
    touch_like = colour_blind_pairs()
    data = PairData(touch_like.targets, touch_like.inputs, touch_like.classes, touch_like.aligned,
                    touch_like.targets.clone(), touch_like.input_pool)
    pairs = pd.DataFrame({"split": "train", "class": data.classes})
    classify = {"width": 0.25, "epochs": 2, "batch_size": 8, "lr": 0.001}
    longer = train_module.build_conditioning("inferred", pairs, "all", data, classify, seed=0, epochs=5)
    default = train_module.build_conditioning("inferred", pairs, "all", data, classify, seed=0)
    assert [(s["epochs"], epochs_run) for s, epochs_run in seen] == [(5, 5), (2, 2)]
    assert {k: v for k, v in seen[0][0].items() if k != "epochs"} == {k: v for k, v in seen[1][0].items() if k != "epochs"}
    assert longer.classifier_settings["epochs"] == 5 and default.classifier_settings["epochs"] == 2
