"""Generate stage and the translate command: what is translated, what is written, what is refused."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from conftest import TINY_MODEL, tiny_params, write_image
from conftest import pair_tables
from vtgen.cli import main
from vtgen.io.checkpoints import load_translator
from vtgen.stages.generate import run_generate, select_inputs, translate, translate_files
from vtgen.core.models import UNetGenerator
from vtgen.io.checkpoints import save_generator

SETTINGS = dict(TINY_MODEL, gan_loss="bce", l1_weight=100.0, optimizer="adam", lr=0.0002, betas=[0.5, 0.999],
                noise=True)


@pytest.fixture
def model_dir(tmp_path):
    torch.manual_seed(0)
    folder = tmp_path / "models/v2t/all"
    folder.mkdir(parents=True)
    save_generator(folder / "generator.pt", UNetGenerator(32, 8, 4), SETTINGS, "v2t", "all")
    return folder


def test_select_inputs_takes_the_test_split_and_a_share_of_training_inputs(tmp_path):
    pairs, splits = pair_tables(tmp_path, per_class=5)
    chosen = select_inputs(splits, pairs, "v2t", "all", train_share=0.5, seed=0)
    assert (chosen["split"] == "test").sum() == 2  # one test source per class
    assert (chosen["split"] == "train").sum() == 4  # half of each class's 4 training inputs
    assert chosen["input_path"].str.contains("/visual/").all()
    assert (chosen["ground_truth_path"] == chosen["input_path"].str.replace("visual", "tactile")).all()
    none = select_inputs(splits, pairs, "v2t", "b", train_share=0.0, seed=0)
    assert list(none["split"]) == ["test"] and list(none["class"]) == ["b"]
    unaligned = select_inputs(splits, pairs.assign(aligned=False), "v2t", "all", 0.0, 0)
    assert (unaligned["ground_truth_path"] == "").all()  # a random partner is not a ground truth


def test_translate_is_deterministic_and_keeps_shape(model_dir):
    generator, meta = load_translator(model_dir)
    assert meta["direction"] == "v2t" and meta["size"] == 32
    images = torch.randint(0, 256, (5, 3, 32, 32), dtype=torch.uint8)
    first, second = translate(generator, images, batch_size=2), translate(generator, images, batch_size=5)
    assert first.dtype == torch.uint8 and first.shape == images.shape
    assert torch.equal(first, second)  # eval mode: no dropout, batch size does not matter


def test_run_generate_writes_images_and_a_linked_table(tmp_path, model_dir, monkeypatch):
    monkeypatch.chdir(tmp_path)
    pairs, splits = pair_tables(tmp_path)
    (tmp_path / "pairs").mkdir()
    pairs.to_parquet("pairs/v2t.parquet")
    pairs.to_parquet("pairs/t2v.parquet")
    splits.to_parquet("pairs/splits.parquet")
    params = tiny_params()
    summary = run_generate(params, "v2t", "pairs", "models/v2t", "generated/v2t", progress=False)
    table = pd.read_parquet("generated/v2t/generated.parquet")
    assert summary["scopes"]["all"]["test"] == 2 and summary["scopes"]["all"]["train"] == 4  # train_share 0.5 of 6
    for row in table.itertuples():
        image = np.asarray(Image.open(row.output_path))
        assert image.shape == (32, 32, 3) and image.dtype == np.uint8
        assert row.ground_truth_path == row.input_path.replace("visual", "tactile")
    assert (tmp_path / "generated/v2t/preview.png").is_file()
    with pytest.raises(ValueError, match="model translates v2t, not t2v"):
        run_generate(params, "t2v", "pairs", "models/v2t", "generated/t2v", progress=False)


def test_translate_files_translates_a_folder(tmp_path, model_dir):
    rng = np.random.default_rng(0)
    for name in ("one", "two"):
        write_image(tmp_path / "in" / f"{name}.png", rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
    np.save(tmp_path / "in" / "three.npy", rng.random((32, 32, 3)))
    written = translate_files(model_dir, [tmp_path / "in"], tmp_path / "out")
    assert sorted(p.name for p in written) == ["one.png", "three.png", "two.png"]
    assert np.asarray(Image.open(written[0])).shape == (32, 32, 3)


@pytest.mark.parametrize("name, array, message", [
    ("small.png", np.zeros((16, 16, 3), np.uint8), "image is 16x16, the model needs 32x32"),
    ("grey.png", np.zeros((32, 32), np.uint8), "image mode is L"),
    ("alpha.png", np.zeros((32, 32, 4), np.uint8), "image mode is RGBA"),
    ("deep.png", np.zeros((32, 32), np.uint16), "image mode is I;16"),
    ("range.npy", np.full((32, 32, 3), 2.0), r"float values must lie in \[0, 1\]"),
    ("nan.npy", np.full((32, 32, 3), np.nan), "NaN or infinite"),
    ("ints.npy", np.zeros((32, 32, 3), np.int64), "unsupported array type int64"),
    ("flat.npy", np.zeros((32, 32), np.uint8), "expected an H x W x 3 array"),
])
def test_translate_refuses_bad_images_with_a_clear_message(tmp_path, model_dir, capsys, name, array, message):
    path = tmp_path / name
    if name.endswith(".npy"):
        np.save(path, array)
    else:
        write_image(path, array)
    code = main(["translate", str(path), "--model", str(model_dir), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith("vtgen translate: error: ") and name in err
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err), err
    assert not (tmp_path / "out").exists()  # nothing is written when an input is refused


def test_translate_refuses_missing_inputs_wrong_direction_and_non_models(tmp_path, model_dir, capsys):
    assert main(["translate", str(tmp_path / "nope.png"), "--model", str(model_dir), "--out", str(tmp_path)]) == 2
    assert "no such file or folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["translate", str(tmp_path / "empty"), "--model", str(model_dir), "--out", str(tmp_path)]) == 2
    assert "no images" in capsys.readouterr().err
    write_image(tmp_path / "ok.png", np.zeros((32, 32, 3), np.uint8))
    assert main(["translate", str(tmp_path / "ok.png"), "--model", str(model_dir), "--out", str(tmp_path / "o"),
                 "--direction", "t2v"]) == 2
    assert "model translates v2t, not t2v" in capsys.readouterr().err
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    assert main(["translate", str(tmp_path / "ok.png"), "--model", str(tmp_path / "junk.pt"), "--out", str(tmp_path)]) == 2
    assert "not a vtgen generator checkpoint" in capsys.readouterr().err
