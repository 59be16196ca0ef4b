"""Generate stage and the translate command: what is translated, what is written, what is refused."""

from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
import torch
from PIL import Image

from conftest import REPO, TINY_MODEL, tiny_params, write_image
from conftest import pair_tables
from vtgen.cli import main
from vtgen.io.checkpoints import load_translator
from vtgen.stages.generate import other_codes, run_generate, select_inputs, translate, translate_files
from vtgen.core.conditioning import Conditioning
from vtgen.core.gan import to_model_range, to_uint8
from vtgen.core.models import UNetGenerator, fixed_codes
from vtgen.io.checkpoints import input_preparation, save_generator
from vtgen.io.images import read_tiles
from vtgen.io.params import ParamsError, validate_params
from vtgen.core.roi import Box, cut_tile

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


def write_pairs_folder(tmp_path, monkeypatch) -> None:
    """Work in ``tmp_path`` with a ``pairs/`` folder of the small v2t pair and split tables."""
    monkeypatch.chdir(tmp_path)
    pairs, splits = pair_tables(tmp_path)
    (tmp_path / "pairs").mkdir()
    pairs.to_parquet("pairs/v2t.parquet")
    splits.to_parquet("pairs/splits.parquet")


def test_truncation_scales_the_latent_codes_towards_the_mean_code():
    """psi 1 is the plain draw bit for bit; psi scales every code (psi 0: the mean code, so the seed no longer
    matters); psi outside [0, 1] is refused."""
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, latent=4).eval()
    images = torch.randint(0, 256, (6, 3, 32, 32), dtype=torch.uint8)
    plain = translate(generator, images, seed=3)
    assert torch.equal(translate(generator, images, seed=3, truncation=1.0), plain)
    with torch.no_grad():
        codes = fixed_codes(generator, len(images), 3)
        expected = to_uint8(generator(to_model_range(images), 0.5 * codes))
    assert torch.equal(translate(generator, images, seed=3, truncation=0.5), expected)
    assert not torch.equal(expected, plain)
    assert torch.equal(translate(generator, images, seed=3, truncation=0.0),
                       translate(generator, images, seed=7, truncation=0.0))
    assert not torch.equal(translate(generator, images, seed=3), translate(generator, images, seed=7))
    for psi in (-0.1, 1.5):
        with pytest.raises(ValueError, match="truncation must lie in"):
            translate(generator, images, truncation=psi)


def test_generate_truncation_is_set_per_direction_and_recorded(tmp_path, monkeypatch):
    """generate.truncation {v2t: psi, t2v: psi}: the written images are translate's at the direction's psi, the
    summary records a psi other than 1 and adds no key at 1, the preview drops its other draws at psi 0; a psi
    outside [0, 1] is refused by the schema."""
    write_pairs_folder(tmp_path, monkeypatch)
    torch.manual_seed(0)
    folder = tmp_path / "models/v2t/all"
    folder.mkdir(parents=True)
    save_generator(folder / "generator.pt", UNetGenerator(32, 8, 4, latent=4), dict(SETTINGS, latent=4), "v2t", "all")
    written = {}
    for psi in (1.0, 0.0):
        params = tiny_params()
        params["generate"]["truncation"] = {"v2t": psi, "t2v": 1.0}
        summary = run_generate(params, "v2t", "pairs", folder.parent, f"generated{psi}", progress=False)
        assert summary["scopes"]["all"].get("truncation") == (None if psi == 1.0 else psi)
        table = pd.read_parquet(f"generated{psi}/generated.parquet")
        written[psi] = np.stack([np.asarray(Image.open(path)) for path in table["output_path"]])
    generator, meta = load_translator(folder)
    first = pd.read_parquet("generated0.0/generated.parquet").iloc[:8]  # the first batch (tiny_params' batch_size 8): seed 0
    expected = translate(generator, read_tiles(list(first["input_path"]), 32), seed=0, truncation=0.0)
    actual = np.stack([np.asarray(Image.open(path)) for path in first["output_path"]])
    assert np.array_equal(actual, expected.permute(0, 2, 3, 1).numpy())
    assert not np.array_equal(written[0.0], written[1.0])
    previews = {psi: np.asarray(Image.open(f"generated{psi}/preview.png")).shape[1] for psi in written}
    assert previews[1.0] - previews[0.0] == 2 * 4 * 96  # psi 0: no columns of other draws (they would be the same image)
    params = tiny_params()
    params["generate"]["truncation"] = 1.5
    with pytest.raises(ParamsError, match="generate.truncation"):
        validate_params(params)


def test_run_generate_writes_images_and_a_linked_table(tmp_path, model_dir, monkeypatch):
    monkeypatch.chdir(tmp_path)
    pairs, splits = pair_tables(tmp_path)
    (tmp_path / "pairs").mkdir()
    pairs.to_parquet("pairs/v2t.parquet")
    pairs.to_parquet("pairs/t2v.parquet")
    splits.to_parquet("pairs/splits.parquet")
    params = tiny_params(generate={"train_share": 0.5})
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


def test_the_preview_shows_other_latent_codes_of_each_input(tmp_path, monkeypatch):
    """A generator with a latent code gets two more columns of outputs per input in the preview (other codes
    of the same inputs); without one the preview keeps its three groups."""
    write_pairs_folder(tmp_path, monkeypatch)
    torch.manual_seed(0)
    widths = {}
    for latent in (0, 4):
        folder = tmp_path / f"models{latent}/v2t/all"
        folder.mkdir(parents=True)
        save_generator(folder / "generator.pt", UNetGenerator(32, 8, 4, latent=latent), dict(SETTINGS, latent=latent),
                       "v2t", "all")
        run_generate(tiny_params(), "v2t", "pairs", folder.parent, f"generated{latent}", progress=False)
        widths[latent] = np.asarray(Image.open(f"generated{latent}/preview.png")).shape[1]
    per_group = 4 * 96  # labelled_sheet: per_class cells of 96 px per group
    assert widths[4] - widths[0] == 2 * per_group
    generator, meta = load_translator(tmp_path / "models4/v2t/all")
    test_rows = pd.read_parquet("generated4/generated.parquet").query("split == 'test'")
    test_rows = test_rows.assign(output_name=test_rows["output_path"])
    draws = other_codes(generator, meta, test_rows)
    written = np.asarray(Image.open(test_rows["output_path"].iloc[0]))
    first = draws[test_rows["output_name"].iloc[0]]
    assert len(first) == 2 and not np.array_equal(first[0], first[1])
    assert first[0].shape == written.shape


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
    ("text.png", None, "not a decodable image"),
    ("range.npy", np.full((32, 32, 3), 2.0), r"float values must lie in \[0, 1\]"),
    ("nan.npy", np.full((32, 32, 3), np.nan), "NaN or infinite"),
    ("ints.npy", np.zeros((32, 32, 3), np.int64), "unsupported array type int64"),
    ("flat.npy", np.zeros((32, 32), np.uint8), "expected an H x W x 3 array"),
])
def test_translate_refuses_bad_images_with_a_clear_message(tmp_path, model_dir, capsys, name, array, message):
    path = tmp_path / name
    if array is None:
        path.write_text("not an image")
    elif name.endswith(".npy"):
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


def test_translate_converts_greyscale_alpha_and_16_bit_tiles_with_notes(tmp_path, model_dir, capsys):
    write_image(tmp_path / "in/grey.png", np.full((32, 32), 7, np.uint8))
    write_image(tmp_path / "in/alpha.png", np.full((32, 32, 4), 9, np.uint8))
    write_image(tmp_path / "in/deep.png", np.full((32, 32), 65535, np.uint16))
    written = translate_files(model_dir, [tmp_path / "in"], tmp_path / "out")
    assert [p.name for p in written] == ["alpha.png", "deep.png", "grey.png"]
    out = capsys.readouterr().out
    for note in ("alpha channel dropped", "16-bit grayscale (I;16) scaled to 8-bit", "grayscale (L) replicated"):
        assert note in out
    generator, _ = load_translator(model_dir)
    white = translate(generator, torch.full((1, 3, 32, 32), 255, dtype=torch.uint8))[0].permute(1, 2, 0).numpy()
    assert np.array_equal(np.asarray(Image.open(tmp_path / "out/deep.png")), white)  # 65535 -> 255


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



VT60_TOUCH = REPO.parent / "shared/data/vt60_subset/touch"
ROI = dict(size=32, tactile_box="full", remove_markers=False, visual_crop="centre", crop_fraction=0.5)


def prepared_model(folder, roi=ROI, direction="t2v", grey=True, model_size=32):
    """A tiny generator saved with a recorded preparation, trained (nominally) on greyscale or colour tiles."""
    torch.manual_seed(0)
    tiles = torch.randint(0, 256, (4, 1 if grey else 3, model_size, model_size), dtype=torch.uint8).expand(4, 3, -1, -1)
    preparation = input_preparation(roi, direction, model_size, tiles)
    folder.mkdir(parents=True)
    save_generator(folder / "generator.pt", UNetGenerator(model_size, 8, 4), dict(SETTINGS, size=model_size), direction,
                   "all", preparation)
    return folder


def grey_frame(tmp_path, name="frame.png"):
    """A raw 640x480 greyscale touch frame: a real VT60 one when the shared data is there, else synthetic."""
    real = sorted(VT60_TOUCH.rglob("*.jpg"))
    if real:
        return real[0], np.asarray(Image.open(real[0]))
    rng = np.random.default_rng(3)
    frame = rng.integers(0, 256, (480, 640), dtype=np.uint8)
    return write_image(tmp_path / name, frame), frame


def test_model_file_records_its_input_preparation(tmp_path):
    model = prepared_model(tmp_path / "m")
    _, meta = load_translator(model)
    prep = meta["preparation"]
    assert prep["input_modality"] == "tactile" and prep["roi"] == ROI and prep["model_size"] == 32
    assert prep["input_channels"] == 1 and "R = G = B in all 4" in prep["input_channels_from"]
    assert meta["note"] == ""
    _, colour = load_translator(prepared_model(tmp_path / "c", direction="v2t", grey=False))
    assert colour["preparation"]["input_channels"] == 3 and colour["preparation"]["input_modality"] == "visual"
    unknown = input_preparation(dict(ROI, tactile_box=(1, 2, 30, 40)), "v2t", 32)
    assert unknown["input_channels"] == 3 and unknown["input_channels_from"].startswith("unknown")
    assert unknown["roi"]["tactile_box"] == [1, 2, 30, 40]
    saved = torch.load(model / "generator.pt", weights_only=False)
    torch.save({**saved, "preparation": {"roi": {}}}, tmp_path / "damaged.pt")
    with pytest.raises(ValueError, match="recorded input preparation is damaged"):
        load_translator(tmp_path / "damaged.pt")


def test_translate_prepares_a_raw_greyscale_frame_with_the_recorded_roi(tmp_path, capsys):
    model = prepared_model(tmp_path / "m")
    frame_path, frame = grey_frame(tmp_path)
    assert frame.shape == (480, 640)
    code = main(["translate", str(frame_path), "--model", str(model), "--out", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert code == 0
    written = tmp_path / "out" / f"{frame_path.stem}.png"
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [written.name]
    image = np.asarray(Image.open(written))
    assert image.shape == (32, 32, 3) and image.dtype == np.uint8
    # the recorded rule, by hand: full frame, centred square of half the shorter side, cut at 32 px
    tile = cut_tile(np.repeat(frame[:, :, None], 3, axis=2), Box(200, 120, 240, 240), 32)
    generator, _ = load_translator(model)
    expected = translate(generator, torch.from_numpy(tile).permute(2, 0, 1)[None])[0].permute(1, 2, 0).numpy()
    assert np.array_equal(image, expected)
    assert "1 images -> 1 tiles of 32 px" in out and "tactile ROI rule" in out
    assert "grayscale (L) replicated to RGB" in out  # read_rgb8's note, reported once per kind


def test_translate_resizes_roi_tiles_to_the_model_size_as_training_did(tmp_path):
    model = prepared_model(tmp_path / "m", roi=dict(ROI, size=64))
    frame = np.random.default_rng(4).integers(0, 256, (120, 160), dtype=np.uint8)
    path = write_image(tmp_path / "in" / "f.png", frame)
    written = translate_files(model, [path], tmp_path / "out")
    tile = cut_tile(np.repeat(frame[:, :, None], 3, axis=2), Box(50, 30, 60, 60), 64)
    write_image(tmp_path / "tile.png", tile)
    generator, _ = load_translator(model)
    expected = translate(generator, read_tiles(["tile.png"], 32, tmp_path))[0].permute(1, 2, 0).numpy()
    assert np.array_equal(np.asarray(Image.open(written[0])), expected)


def test_translate_gives_colour_to_a_greyscale_model_as_grey_and_cuts_several_tiles(tmp_path, capsys):
    model = prepared_model(tmp_path / "m", roi=dict(ROI, visual_crop="tiles", crop_fraction=0.5))
    rng = np.random.default_rng(5)
    write_image(tmp_path / "in" / "photo.png", rng.integers(0, 256, (64, 128, 3), dtype=np.uint8))
    written = translate_files(model, [tmp_path / "in"], tmp_path / "out")
    assert [p.name for p in written] == [f"photo_{k}.png" for k in range(8)]  # a 4 x 2 grid of 32 px squares
    assert "colour converted to greyscale" in capsys.readouterr().out
    write_image(tmp_path / "in" / "photo_0.png", np.zeros((1, 1, 3), np.uint8))  # a grid of one 1-px tile
    with pytest.raises(ValueError, match=r"photo_0\.png: its output .*photo_0\.png would overwrite that of .*photo\.png"):
        translate_files(model, [tmp_path / "in"], tmp_path / "out2")
    assert not (tmp_path / "out2").exists()


def test_translate_keeps_relative_paths_and_refuses_collisions(tmp_path, capsys):
    model = prepared_model(tmp_path / "m")
    rng = np.random.default_rng(6)
    for sub in ("a", "b/deeper"):
        write_image(tmp_path / "in" / sub / "x.png", rng.integers(0, 256, (48, 64), dtype=np.uint8))
    written = translate_files(model, [tmp_path / "in"], tmp_path / "out")
    assert written == [tmp_path / "out/a/x.png", tmp_path / "out/b/deeper/x.png"]
    assert not np.array_equal(*(np.asarray(Image.open(p)) for p in written))  # two outputs, none lost
    a, b = tmp_path / "in/a/x.png", tmp_path / "in/b/deeper/x.png"
    code = main(["translate", str(a), str(b), "--model", str(model), "--out", str(tmp_path / "o1")])
    err = capsys.readouterr().err
    assert code == 2 and str(a) in err and str(b) in err and "would overwrite" in err
    assert not (tmp_path / "o1").exists()
    write_image(tmp_path / "in/a/x.jpg", rng.integers(0, 256, (48, 64), dtype=np.uint8))  # x.png and x.jpg: one x.png
    code = main(["translate", str(tmp_path / "in"), "--model", str(model), "--out", str(tmp_path / "o2")])
    err = capsys.readouterr().err
    assert code == 2 and "in/a/x.jpg" in err and "in/a/x.png" in err
    assert not (tmp_path / "o2").exists()


def test_translate_names_every_bad_file_at_once_and_writes_nothing(tmp_path, capsys):
    model = prepared_model(tmp_path / "m")
    rng = np.random.default_rng(7)
    folder = tmp_path / "in"
    write_image(folder / "good.png", rng.integers(0, 256, (48, 64), dtype=np.uint8))
    (folder / "notes.png").write_text("not an image at all")
    cut = write_image(folder / "sub" / "cut.jpg", rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    write_image(folder / "tiny.png", np.zeros((1, 1), np.uint8))  # half of 1 px: no crop
    code = main(["translate", str(folder), "--model", str(model), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2
    lines = err.strip().splitlines()
    assert lines[0] == "vtgen translate: error: 3 problems in 4 inputs; nothing translated:"
    reasons = dict(line.strip().split(": ", 1) for line in lines[1:])
    assert set(reasons) == {str(folder / "notes.png"), str(folder / "sub/cut.jpg"), str(folder / "tiny.png")}
    assert "not a decodable image" in reasons[str(folder / "notes.png")]
    assert "truncated" in reasons[str(folder / "sub/cut.jpg")]
    assert "too small" in reasons[str(folder / "tiny.png")]
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".out*"))  # no output, no staging left


def test_translate_with_an_old_model_file_needs_tiles_of_its_size(tmp_path, capsys):
    record = {"state_dict": UNetGenerator(32, 8, 4).state_dict(), "settings": SETTINGS, "direction": "t2v",
              "scope": "all", "input_modality": "tactile", "output_modality": "visual"}  # as written before preparation
    torch.save(record, tmp_path / "old.pt")
    _, meta = load_translator(tmp_path / "old.pt")
    assert meta["preparation"] is None and "no input preparation recorded" in meta["note"]
    rng = np.random.default_rng(8)
    write_image(tmp_path / "in/tile.png", rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
    written = translate_files(tmp_path / "old.pt", [tmp_path / "in"], tmp_path / "out")
    assert [p.name for p in written] == ["tile.png"]
    assert "no input preparation recorded" in capsys.readouterr().out
    frame_path, _ = grey_frame(tmp_path)
    code = main(["translate", str(frame_path), "--model", str(tmp_path / "old.pt"), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "image is 640x480, the model needs 32x32" in err and str(frame_path) in err


def test_translate_as_tiles_skips_the_roi_rule(tmp_path):
    model = prepared_model(tmp_path / "m")
    tile = np.random.default_rng(9).integers(0, 256, (64, 64), dtype=np.uint8)
    path = write_image(tmp_path / "t.png", tile)
    written = translate_files(model, [path], tmp_path / "out", as_tiles=True)
    write_image(tmp_path / "rgb.png", np.repeat(tile[:, :, None], 3, axis=2))
    generator, _ = load_translator(model)
    expected = translate(generator, read_tiles(["rgb.png"], 32, tmp_path))[0].permute(1, 2, 0).numpy()
    assert np.array_equal(np.asarray(Image.open(written[0])), expected)


@pytest.mark.slow
def test_run_train_records_the_preparation_of_its_training_data(tmp_path, monkeypatch):
    from vtgen.stages.train import run_train

    write_pairs_folder(tmp_path, monkeypatch)
    params = tiny_params()
    run_train(params, "v2t", "all", "pairs", "models/v2t/all", "ckpt", progress=False)
    _, meta = load_translator("models/v2t/all")
    prep = meta["preparation"]
    assert prep["roi"] == {k: params["roi"][k] for k in ROI} and prep["input_modality"] == "visual"
    assert prep["model_size"] == 32 and prep["input_channels"] == 3  # pair_tables' tiles are random colour


def coloured_class_pairs(tmp_path, monkeypatch) -> pd.DataFrame:
    """The small v2t pairs folder as class pairs, with tiles a feature reader can read: class a reddish, class b
    bluish, except b's test photo, which is reddish (so it is read as a). Returns the split table."""
    write_pairs_folder(tmp_path, monkeypatch)
    pairs = pd.read_parquet("pairs/v2t.parquet").assign(aligned=False, pair_kind="class")
    pairs.to_parquet("pairs/v2t.parquet")
    splits = pd.read_parquet("pairs/splits.parquet")
    rng = np.random.default_rng(5)
    for row in splits.itertuples():
        reddish = row[2] == "a" or (row.split == "test" and row.modality == "visual")  # row[2]: the class column
        tile = rng.integers(0, 8, (32, 32, 3), dtype=np.uint8)
        tile[..., 0 if reddish else 2] += 180
        write_image(tmp_path / row.path, tile)
    return splits


def test_a_generator_told_the_class_also_translates_each_test_input_told_the_class_read_from_it(tmp_path,
                                                                                                monkeypatch):
    """Issue 24, goal 3 for a generator told the class: under the class-pair objective the stage also writes each
    test input translated told the class a feature reader (fitted on the training inputs) reads from it (split
    test_read, the input's true class), with the plain test outputs' latent codes, so an input read right gets the
    identical image and one read wrong gets the other class's; the summary counts the reading, and the preview shows
    them in a group of their own. A pix2pix model told the class writes no such rows."""
    splits = coloured_class_pairs(tmp_path, monkeypatch)
    assert list(splits.columns[:2]) == ["path", "class"]
    conditioning = Conditioning("class", ("a", "b"))
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, 4, in_channels=3 + conditioning.extra_channels, latent=4)
    for name, settings in (("gan", dict(SETTINGS, latent=4, objective="class_gan")), ("pix", dict(SETTINGS, latent=4))):
        (tmp_path / f"models_{name}/v2t/all").mkdir(parents=True)
        save_generator(tmp_path / f"models_{name}/v2t/all/generator.pt", generator, settings, "v2t", "all",
                       conditioning=conditioning)
    summary = run_generate(tiny_params(), "v2t", "pairs", "models_gan/v2t", "generated", progress=False)
    table = pd.read_parquet("generated/generated.parquet")
    test, read = (table[table["split"] == s].sort_values("input_path") for s in ("test", "test_read"))
    assert list(read["input_path"]) == list(test["input_path"]) and list(read["class"]) == ["a", "b"]
    assert summary["scopes"]["all"]["told_the_class_read"] == {"reader": "features", "inputs": 2, "read_correctly": 1,
                                                               "read_accuracy": 0.5}
    pixels = {p: np.asarray(Image.open(p)) for p in list(test["output_path"]) + list(read["output_path"])}
    a_test, b_test = test["output_path"]
    a_read, b_read = read["output_path"]
    assert np.array_equal(pixels[a_read], pixels[a_test])  # read right: the same image
    assert not np.array_equal(pixels[b_read], pixels[b_test])  # b's photo is read as a
    model, meta = load_translator("models_gan/v2t/all")
    batch = table[table["split"] != "test_read"].iloc[:8]  # the stage's first batch (tiny_params' batch_size 8), seed 0
    assert list(batch["split"][:2]) == ["test", "test"]
    labels = conditioning.labels(list(batch["class"]))
    labels[1] = 0  # b's test photo told a, as read
    expected = translate(model, read_tiles(list(batch["input_path"]), 32), conditioning=conditioning, labels=labels,
                         seed=0)
    assert np.array_equal(pixels[b_read], expected[1].permute(1, 2, 0).numpy())
    run_generate(tiny_params(), "v2t", "pairs", "models_pix/v2t", "generated_pix", progress=False)
    assert "test_read" not in set(pd.read_parquet("generated_pix/generated.parquet")["split"])
    preview, plain = (np.asarray(Image.open(f"{folder}/preview.png")) for folder in ("generated", "generated_pix"))
    assert preview.shape[1] - plain.shape[1] == 4 * 96  # one more group: the outputs told the class read
    group = 120 + 4 * 4 * 96  # label column, then input, generated, codes 2 and 3: the group after them
    cell = np.asarray(Image.fromarray(pixels[b_read]).resize((96, 96), Image.NEAREST))
    assert np.array_equal(preview[24 + 96:24 + 2 * 96, group:group + 96], cell)  # class b's row, its first input
