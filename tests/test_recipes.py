"""translation.recipe: a named block of dotted-key settings applied over params.yaml (io/params.with_recipe), or
auto: the fabric block for class pairs of texture photos, else none (io/params.recipe_choice)."""

import argparse
import copy
import json

import pytest

from vtgen.cli import run_stage
from PIL import Image
import numpy as np

from vtgen.cli import data_kind
from vtgen.core.layout import layout_gap
from vtgen.io.params import ParamsError, direction_settings, recipe_choice, validate_params, with_recipe
from vtgen.pipeline import STAGES, params_text

TEXTURES = {"class_pairs_only": True, "classes": 12, "layout_gap": 0.13}  # the synthetic fabrics' training photos
SCENES = {"class_pairs_only": True, "classes": 10, "layout_gap": 0.76}    # vt60_subset's object photos


def choose(params: dict, recipe: str) -> dict:
    chosen = copy.deepcopy(params)
    chosen["translation"]["recipe"] = recipe
    return chosen


def value_at(params: dict, key: str):
    node = params
    for part in key.split("."):
        node = node[part]
    return node


def test_none_is_params_as_written(default_params):
    named = choose(default_params, "none")
    assert with_recipe(named) is named


def test_auto_chooses_fabric_for_class_pairs_of_texture_photos_only(default_params):
    assert default_params["translation"]["recipe"] == "auto"
    fabric, none = with_recipe(choose(default_params, "fabric")), choose(default_params, "none")
    assert with_recipe(default_params, TEXTURES) == fabric
    for kind in (SCENES, {"class_pairs_only": False, "classes": 12, "layout_gap": None}, {**TEXTURES, "layout_gap": None},
                 {**TEXTURES, "classes": 1}, None):  # pixel pairs, no photos, one cloth, no summary
        assert with_recipe(default_params, kind) == none, kind
    assert recipe_choice(default_params, {**TEXTURES, "layout_gap": 0.4})[0] == "fabric"  # the bound is in
    assert recipe_choice(default_params, {**TEXTURES, "layout_gap": 0.41})[0] == "none"
    name, reason = recipe_choice(default_params, SCENES)
    assert name == "none" and "scenes" in reason and "0.76" in reason
    # the aligned default (pixel pairs) trains exactly as under recipe none: its settings files are byte-identical
    pixel = {"class_pairs_only": False, "classes": 12, "layout_gap": None}
    for direction in ("v2t", "t2v"):
        assert direction_settings(default_params, direction, pixel) == direction_settings(none, direction)


def test_the_layout_gap_tells_a_texture_from_a_scene():
    """gap = sd of the 4 x 4 block means / sd of the pixels (core/layout.py), on known images."""
    rng = np.random.default_rng(0)
    stripes = np.tile(np.repeat([0, 255], 2), 16)[None, :].repeat(64, 0).astype(np.uint8)  # period 4 px
    noise = rng.integers(0, 256, (64, 64), dtype=np.uint8)
    halves = np.zeros((64, 64), np.uint8)
    halves[:, 32:] = 255                                                                    # one edge: a layout
    disc = np.zeros((64, 64), np.uint8)
    yy, xx = np.mgrid[:64, :64]
    disc[(yy - 32) ** 2 + (xx - 32) ** 2 < 20 ** 2] = 200                                   # an object on a ground
    gap = {name: layout_gap(Image.fromarray(a)) for name, a in
           (("stripes", stripes), ("noise", noise), ("halves", halves), ("disc", disc))}
    assert gap["stripes"] < 0.01 and gap["noise"] < 0.1        # white noise: about 1 / 16
    assert gap["halves"] == pytest.approx(1.0) and gap["disc"] > 0.7
    assert layout_gap(Image.fromarray(np.full((64, 64), 90, np.uint8))) == 0.0


def test_auto_reads_the_pairs_summary_and_names_it_when_missing(default_params, tmp_path):
    args = argparse.Namespace(stage="settings", pairs=str(tmp_path / "pairs"))
    with pytest.raises(ValueError, match=r"pairs/summary\.json: no pairs summary; translation\.recipe 'auto'"):
        data_kind(args, default_params)
    assert data_kind(argparse.Namespace(stage="classify", pairs=str(tmp_path / "pairs")), default_params) is None
    (tmp_path / "pairs").mkdir()
    (tmp_path / "pairs" / "summary.json").write_text(json.dumps({"data_kind": TEXTURES}))
    assert data_kind(args, default_params) == TEXTURES
    assert data_kind(args, choose(default_params, "none")) is None  # a named recipe reads nothing
    assert data_kind(argparse.Namespace(), default_params) is None   # a stage without pairs


@pytest.mark.parametrize("recipe", ["fabric", "quick"])
def test_a_recipe_sets_each_of_its_keys_and_nothing_else(default_params, recipe):
    raw = choose(default_params, recipe)
    before = copy.deepcopy(raw)
    applied = with_recipe(raw)
    block = raw["recipes"][recipe]
    assert block, "the shipped recipes are not empty"
    for key, value in block.items():
        assert value_at(applied, key) == value, key
    assert raw == before  # params.yaml as read is left alone: the records hash it
    assert with_recipe(applied) == applied  # the name stays, applying again changes nothing
    # every other key keeps its value: undo the block's keys and compare the whole tree
    undone = copy.deepcopy(applied)
    for key in block:
        *parents, leaf = key.split(".")
        node = undone
        for part in parents:
            node = node[part]
        node[leaf] = value_at(raw, key)
    assert undone == raw


def test_the_quick_recipe_restores_the_short_class_pair_settings(default_params):
    """By default a class-pair V2T reads the photo's class with the features and trains 6,000 steps with a
    teaching discriminator (R1 1), and T2V trains 3,000 (R1 1 too, with decoder noise); `quick` gives the earlier, shorter settings back (the preset's
    1,500 steps for both)."""
    translation = default_params["translation"]
    assert translation["conditioning"] == {"v2t": "auto", "t2v": "class"}
    assert translation["inferred_reader"] == "features"
    assert translation["class_gan"]["r1"] == {"v2t": 1, "t2v": 1}
    assert translation["class_gan"]["iterations"] == {"v2t": 6000, "t2v": 3000}
    quick = with_recipe(choose(default_params, "quick"))["translation"]
    assert quick["conditioning"] == {"v2t": "none", "t2v": "class"}
    assert quick["class_gan"]["r1"] == 240 and quick["class_gan"]["iterations"] is None
    # and T2V's generator and discriminator of then: transposed convs, no noise maps, no anti-aliasing in D
    assert (quick["class_gan"]["upsample"], quick["class_gan"]["decoder_noise"], quick["class_gan"]["d_antialias"]) == (
        "transpose", 0, False)


def test_the_fabric_recipe_keeps_the_reader_it_was_measured_with(default_params):
    applied = with_recipe(choose(default_params, "fabric"))["translation"]
    assert applied["inferred_reader"] == "network" and applied["conditioning"] == {"v2t": "inferred", "t2v": "inferred"}
    # and its generators as measured in the Seventy-fifth round: V2T's resize decoder with a plain D; T2V's balanced
    # decoder under an anti-aliased D with R1 1 (the default's bilinear decoder and noise maps lost the weave there)
    class_gan = applied["class_gan"]
    assert (class_gan["upsample"], class_gan["decoder_noise"], class_gan["d_antialias"], class_gan["r1"]) == (
        {"v2t": "resize", "t2v": "balanced"}, 0, {"v2t": False, "t2v": True}, 1)


@pytest.mark.parametrize("edit, message", [
    (lambda p: p["translation"].update(recipe="fabrik"), r"translation\.recipe: 'fabrik' is not a block of recipes"),
    (lambda p: p["recipes"]["quick"].update({"classify.epochs": 3}), r"recipes\.quick: unknown key 'classify\.epochs'"),
    (lambda p: p["recipes"]["quick"].update({"translation.scope": ["denim"]}),
     r"recipes\.quick\.translation\.scope: set it in params\.yaml itself"),
    (lambda p: p["recipes"]["quick"].update({"translation.class_gan.r2": 1}),
     r"recipes\.quick\.translation\.class_gan\.r2: params has no key"),
    (lambda p: p["recipes"]["fabric"].update({"translation.class_gan.select_every": {"v2t": "often", "t2v": 1}}),
     r"recipes\.fabric\.translation\.class_gan\.select_every\.v2t: 'often' is not of type 'integer'"),
    (lambda p: p["recipes"]["none"].update({"generate.seed": 1}), r"recipes\.none: .* is expected to be empty"),
    (lambda p: p["recipes"].update(auto={}), r"recipes\.auto: 'auto' is translation\.recipe's choice"),
    (lambda p: p["recipes"].pop("fabric"), r"translation\.recipe: 'auto' chooses among fabric, none; recipes has no block fabric"),
])
def test_a_bad_recipe_is_refused_naming_the_key(default_params, edit, message):
    params = copy.deepcopy(default_params)
    edit(params)
    with pytest.raises(ParamsError, match=message):
        validate_params(params)


def records(params: dict) -> dict[str, str]:  # one per stage, and per direction for the settings stage
    return {s.name + (f"@{d}" if s.record_by else ""): params_text(s, params, {"direction": d})
            for s in STAGES for d in ("v2t", "t2v")}


def test_training_depends_on_the_recipes_it_may_apply_only(default_params):
    """Editing the chosen recipe changes the params record of the settings job of the direction it changes (which
    training depends on), generate and report; editing another recipe changes no settings record (so no training
    reruns; generate, report and the studies, which read every block, do)."""
    chosen = choose(default_params, "quick")
    edited_chosen = copy.deepcopy(chosen)
    assert chosen["recipes"]["quick"]["translation.class_gan.r1"] == 240
    edited_chosen["recipes"]["quick"]["translation.class_gan.r1"] = {"v2t": 2, "t2v": 240}  # V2T's value alone
    edited_other = copy.deepcopy(chosen)
    edited_other["recipes"]["fabric"]["translation.class_gan.ema"] = 0.99
    before, after = records(chosen), records(edited_chosen)
    changed = {name for name in before if before[name] != after[name]}
    assert {"settings@v2t", "generate", "report"} <= changed
    assert not {"settings@t2v", "classify", "score"} & changed
    other = records(edited_other)
    assert {name for name in before if before[name] != other[name]} == {"generate", "report", "tradeoff_setting",
                                                                         "experiment", "stability"}


def test_under_auto_either_block_it_may_choose_retrains_what_it_sets(default_params):
    """Snakemake records the settings job before any data exists, so under auto the record holds the settings of
    both blocks auto may choose: editing the fabric block's V2T value reruns V2T's settings job only; editing the
    quick block (never chosen by auto) reruns none."""
    fabric_v2t = copy.deepcopy(default_params)
    fabric_v2t["recipes"]["fabric"]["translation.class_gan.nce"] = {"v2t": 0.2, "t2v": 0.0}
    quick = copy.deepcopy(default_params)
    quick["recipes"]["quick"]["translation.class_gan.r1"] = 120
    before = records(default_params)
    assert {n for n, text in records(fabric_v2t).items() if text != before[n] and n.startswith("settings")} == {"settings@v2t"}
    assert {n for n, text in records(quick).items() if text != before[n] and n.startswith("settings")} == set()


def test_a_stage_command_runs_with_the_recipe_applied(default_params, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    seen = {}
    args = argparse.Namespace(stage="train", params="params.yaml", out=str(tmp_path / "out"),
                              func=lambda a, p: seen.update(params=p))
    run_stage(args, choose(default_params, "fabric"))
    applied = seen["params"]
    assert applied["translation"]["class_gan"]["iterations"] == 12000
    assert applied["generate"]["truncation"] == {"v2t": 0, "t2v": 1}
    assert json.loads(json.dumps(applied))["translation"]["recipe"] == "fabric"


def test_classify_seeds_follow_the_data_kind():
    """A list of seeds is used as set; a mapping gives class_pairs only where every training pair is a class pair."""
    from vtgen.stages.classify import classify_seeds

    mapping = {"paired": [0, 1, 2], "class_pairs": [0, 1, 2, 3, 4]}
    assert classify_seeds([7, 8], {"class_pairs_only": True}) == ([7, 8], "as set")
    assert classify_seeds(mapping, {"class_pairs_only": True})[0] == [0, 1, 2, 3, 4]
    assert classify_seeds(mapping, {"class_pairs_only": False})[0] == [0, 1, 2]
    assert classify_seeds(mapping, None) == ([0, 1, 2], "no pairs summary, so the paired list")


def test_classify_seeds_mapping_needs_both_lists(default_params):
    """A mapping without one of its two lists is refused, naming the key."""
    params = copy.deepcopy(default_params)
    params["classify"]["seeds"] = {"paired": [0]}
    with pytest.raises(ValueError, match="classify.seeds"):
        validate_params(params)
