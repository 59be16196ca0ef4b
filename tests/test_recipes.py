"""translation.recipe: a named block of dotted-key settings applied over params.yaml (io/params.with_recipe)."""

import argparse
import copy
import json

import pytest

from vtgen.cli import run_stage
from vtgen.io.params import ParamsError, validate_params, with_recipe
from vtgen.pipeline import STAGES, params_text


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
    assert default_params["translation"]["recipe"] == "none"
    assert with_recipe(default_params) is default_params


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
    teaching discriminator (R1 1); `quick` gives the earlier, shorter settings back. T2V is left as it is."""
    translation = default_params["translation"]
    assert translation["conditioning"] == {"v2t": "auto", "t2v": "class"}
    assert translation["inferred_reader"] == "features"
    assert translation["class_gan"]["r1"] == {"v2t": 1, "t2v": 240}
    assert translation["class_gan"]["iterations"] == {"v2t": 6000, "t2v": None}
    quick = with_recipe(choose(default_params, "quick"))["translation"]
    assert quick["conditioning"] == {"v2t": "none", "t2v": "class"}
    assert quick["class_gan"]["r1"] == 240 and quick["class_gan"]["iterations"] is None


def test_the_fabric_recipe_keeps_the_reader_it_was_measured_with(default_params):
    applied = with_recipe(choose(default_params, "fabric"))["translation"]
    assert applied["inferred_reader"] == "network" and applied["conditioning"] == {"v2t": "inferred", "t2v": "inferred"}


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
])
def test_a_bad_recipe_is_refused_naming_the_key(default_params, edit, message):
    params = copy.deepcopy(default_params)
    edit(params)
    with pytest.raises(ParamsError, match=message):
        validate_params(params)


def test_stages_that_read_translation_depend_on_the_chosen_recipe_only(default_params):
    """Editing the chosen recipe changes the params record of the settings job of the direction it changes (which
    training depends on), generate and report; editing another recipe changes no stage's record (so it reruns nothing)."""
    def records(params: dict) -> dict[str, str]:  # one per stage, and per direction for the settings stage
        return {s.name + (f"@{d}" if s.record_by else ""): params_text(s, params, {"direction": d})
                for s in STAGES for d in ("v2t", "t2v")}

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
    assert records(edited_other) == before


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
