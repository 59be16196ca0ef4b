"""class_gan.select_every: a run scores its generator every n steps by the classifier-view FID of its translated
validation inputs and yields the best snapshot (the referee's scale, the choice, a resumed run's choice, the
switch's off state and train.json's record); the same classifier as capacity auto's judge of class pairs."""

from __future__ import annotations

import copy

import pytest
import torch
from torch import nn

from test_class_gan import CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.conditioning import Conditioning
from vtgen.stages.train import (build_judge, checkpoint_keys, objective_settings, PairData, recognition_floor, selection_record,
                               train_translator, validation_by_class)
from vtgen.core.referee import distinct_images, train_referee

CLASSIFY = {"size": 32, "width": 0.25, "epochs": 4, "batch_size": 8, "lr": 1e-3}
RUN = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=100, resume=False, log_every=1, seed=0)


class Echo(nn.Module):
    """A 'generator' that returns its input image: translating real targets gives the real targets back."""

    latent = 0

    def __init__(self):
        super().__init__()
        self.unused = nn.Parameter(torch.zeros(1))  # translate reads the device from a parameter

    def forward(self, x, z=None):
        return x[:, :3]


class Flat(Echo):
    def forward(self, x, z=None):
        return torch.zeros_like(x[:, :3])


class Scripted:
    """A referee whose scores are given in advance (one per call), to test the choice apart from the metric."""

    def __init__(self, scores):
        self.scores = list(scores)

    def score(self, generator, conditioning):
        return self.scores.pop(0)


def test_the_referee_scores_real_images_near_zero_and_a_flat_image_far_off():
    data = rendered_class_pairs(4, 32, seed=0)
    referee = train_referee(data.targets, data.classes, data.targets, data.classes, CLASSIFY, seed=0)
    assert len(referee.reference) == len(distinct_images(data.targets)) == len(data.targets)
    real = referee.score(Echo(), Conditioning())
    flat = referee.score(Flat(), Conditioning())
    assert real < 1e-6 < flat
    assert flat > 100 * max(real, 1e-6)


def test_the_run_yields_the_snapshot_with_the_lowest_validation_fid():
    data = rendered_class_pairs(4, 32, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=6, select_every=2)
    chosen = train_translator(data, settings, RUN, "v2t", "all", progress=False, referee=Scripted([3.0, 1.0, 2.0]))
    assert [r.get("val_fid") for r in chosen.history if "val_fid" in r] == [3.0, 1.0, 2.0]
    assert [r["step"] for r in chosen.history if "val_fid" in r] == [2, 4, 6]
    assert chosen.selected == {"step": 4, "val_fid": 1.0} and chosen.steps == 6
    # the weights are step 4's: a run of exactly 4 steps (same seed, constant learning rate) ends there
    four = train_translator(data, dict(settings, iterations=4, select_every=0), RUN, "v2t", "all", progress=False)
    last = train_translator(data, dict(settings, select_every=0), RUN, "v2t", "all", progress=False)
    for name, weight in chosen.generator.state_dict().items():
        assert torch.equal(weight, four.generator.state_dict()[name]), name
    assert any(not torch.equal(w, last.generator.state_dict()[n]) for n, w in chosen.generator.state_dict().items())
    assert four.selected is None  # select_every 0 keeps the last step's generator
    # a selection step that is not a logging step still closes a window and is scored
    odd = train_translator(data, dict(settings, select_every=2), dict(RUN, log_every=5), "v2t", "all", progress=False,
                           referee=Scripted([4.0, 3.0, 5.0]))
    assert [r["step"] for r in odd.history if "val_fid" in r] == [2, 4, 6] and odd.selected["step"] == 4


def test_a_resumed_run_selects_as_an_uninterrupted_one(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    validation = rendered_class_pairs(2, 32, seed=1)
    referee = train_referee(data.targets, data.classes, validation.inputs, validation.classes, CLASSIFY, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=6, select_every=2)
    whole = train_translator(data, settings, RUN, "v2t", "all", progress=False, referee=referee)
    run = dict(RUN, checkpoint_every=2, resume=True)
    train_translator(data, dict(settings, iterations=4), run, "v2t", "all", tmp_path, progress=False, referee=referee)
    resumed = train_translator(data, settings, run, "v2t", "all", tmp_path, progress=False, referee=referee)
    assert resumed.resumed_from == 4
    assert resumed.selected == whole.selected
    assert [r["val_fid"] for r in resumed.history if "val_fid" in r] == [r["val_fid"] for r in whole.history if "val_fid" in r]
    for name, weight in whole.generator.state_dict().items():
        assert torch.equal(weight, resumed.generator.state_dict()[name]), name


def test_off_adds_no_settings_key_a_value_may_be_given_per_direction_and_train_json_says_which_step(default_params):
    from vtgen.io.params import ParamsError, validate_params
    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["select_every"] == {"v2t": 0, "t2v": 250}  # T2V selects by default
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")["select_every"] == 250
    params["translation"]["class_gan"]["select_every"] = 0
    plain = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")
    plain_v2t = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")  # the defaults differ by direction
    assert "select_every" not in plain  # so 0's checkpoint keys are those of the code before the switch
    params["translation"]["class_gan"]["select_every"] = {"v2t": 0, "t2v": 500}
    validate_params(params)
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")["select_every"] == 500
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t") == plain_v2t
    params["translation"]["class_gan"]["select_every"] = -1
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.select_every"):
        validate_params(params)
    data = rendered_class_pairs(4, 32, seed=0)
    settings = dict(SETTINGS, **CLASS_GAN, iterations=4, select_every=2)
    result = train_translator(data, settings, RUN, "v2t", "all", progress=False, referee=Scripted([2.0, 5.0]))
    record = selection_record(settings, result, data)
    assert record["step"] == 2 and record["val_fid"] == 2.0 and record["val_fid_by_step"] == {2: 2.0, 4: 5.0}
    no_validation = train_translator(data, settings, RUN, "v2t", "all", progress=False)
    assert selection_record(settings, no_validation, None) == {
        "every": 2, "step": 4, "reason": "the last step's generator (nothing to select by, or no selection step was reached)"}
    assert "training inputs (no validation split)" in selection_record(settings, result, None)["reason"]


def test_the_report_names_the_step_whose_generator_was_kept():
    from vtgen.io.report_tables import models_table
    chosen = {"every": 1000, "step": 10000, "val_fid": 116.1, "reason": "the snapshot with the lowest ..."}
    table = models_table([{"direction": "t2v", "scope": "all", "steps": 12000, "selection": chosen},
                          {"direction": "v2t", "scope": "all", "steps": 1500}])
    assert table["iterations"].tolist() == [12000, 1500]
    assert table["generator kept"].tolist()[0] == 10000 and table["generator kept"].isna().tolist()[1]
    assert table["kept because"].tolist()[0] == chosen["reason"]


def test_without_validation_pairs_the_referee_translates_a_sample_of_training_inputs_and_says_so(capsys):
    from vtgen.stages.train import build_referee, SELECTION_INPUTS_PER_CLASS
    data = rendered_class_pairs(4, 32, seed=0)
    validation = rendered_class_pairs(2, 32, seed=1)
    assert build_referee(dict(SETTINGS, select_every=0), data, validation, CLASSIFY, seed=0) is None
    referee = build_referee(dict(SETTINGS, select_every=250), data, validation, CLASSIFY, seed=0)
    assert referee is not None and torch.equal(referee.inputs, validation.inputs)

    sampled = build_referee(dict(SETTINGS, select_every=250), data, None, CLASSIFY, seed=0)
    assert "no validation split" in capsys.readouterr().out
    per_class = {name: sampled.classes.count(name) for name in set(sampled.classes)}
    pools = {name: len(pool) for name, pool in data.input_pool.items()}
    assert per_class == {name: min(size, SELECTION_INPUTS_PER_CLASS) for name, size in pools.items()}
    for image, name in zip(sampled.inputs, sampled.classes):  # each a training input of its own class, none repeated
        assert any(torch.equal(image, data.pool_images[i]) for i in data.input_pool[name])
    assert len(distinct_images(sampled.inputs)) == len(sampled.inputs)
    again = build_referee(dict(SETTINGS, select_every=250), data, None, CLASSIFY, seed=0)
    assert torch.equal(again.inputs, sampled.inputs)  # the same sample at the same seed

    one_class = PairData(data.inputs[:1], data.targets[:1], data.classes[:1], data.aligned[:1], data.pool_images,
                         {data.classes[0]: data.input_pool[data.classes[0]]})
    assert build_referee(dict(SETTINGS, select_every=250), one_class, None, CLASSIFY, seed=0) is None
    assert "fewer than two classes" in capsys.readouterr().out


# ---------------------------------------------------------------- capacity auto's judge (capacity.class_signal)

JUDGE_CLASSIFY = dict(CLASSIFY, epochs=25)


def echoed(data):
    """Class pairs whose inputs are their own targets, so Echo 'translates' each input into a real target."""
    return PairData(data.targets.clone(), data.targets.clone(), list(data.classes), data.aligned.clone(),
                    data.targets.clone(), data.input_pool)


def test_the_judge_gives_real_images_their_class_and_a_flat_image_the_chance_level():
    data = rendered_class_pairs(4, 32, seed=0)
    judge = train_referee(data.targets, data.classes, data.inputs, data.classes, JUDGE_CLASSIFY, seed=0)
    real = judge.recognition(data.targets, data.classes)
    flat = judge.recognition(torch.zeros_like(data.targets), data.classes)
    assert real.shape == (len(data.targets),) and bool(((real >= 0) & (real <= 1)).all())
    assert float(real.mean()) > 0.6  # three classes: chance 1/3
    assert float(flat.mean()) == pytest.approx(1 / 3, abs=1e-6)  # one image for all: its probabilities average to 1/3
    assert float(judge.recognition(data.targets[:2], ["velvet", "velvet"]).sum()) == 0.0  # a class it never saw


def test_with_a_judge_a_class_pair_scores_its_recognition_minus_the_spread_gap():
    data = echoed(rendered_class_pairs(4, 32, seed=0))
    judge = train_referee(data.targets, data.classes, data.inputs, data.classes, JUDGE_CLASSIFY, seed=0)
    judged = validation_by_class(Echo(), data, judge=judge)
    for name in set(data.classes):  # Echo's outputs are the real targets: spread ratio 1, no penalty
        rows = [i for i, c in enumerate(data.classes) if c == name]
        assert judged[name] == pytest.approx(float(judge.recognition(data.targets[rows], [name] * len(rows)).mean()))
    flat = validation_by_class(Flat(), data, judge=judge)
    assert all(flat[name] < judged[name] - 0.5 for name in judged)  # collapsed (collapse gap 1) and unrecognised
    assert validation_by_class(Echo(), data) != judged  # without a judge: the colour and contrast score
    # outputs spread four times as much as the real targets: no gap with a judge, the full spread gap without
    faint = PairData(data.inputs, (data.targets // 4 + 96).to(torch.uint8), data.classes, data.aligned,
                     data.pool_images, data.input_pool)
    wide = validation_by_class(Echo(), faint, judge=judge)
    for name in set(data.classes):
        rows = [i for i, c in enumerate(data.classes) if c == name]
        assert wide[name] == pytest.approx(float(judge.recognition(data.inputs[rows], [name] * len(rows)).mean()))
    assert all(score < -0.9 for score in validation_by_class(Echo(), faint).values())


def test_the_judge_is_built_only_for_recognition_and_classes_without_aligned_validation_pairs():
    data = rendered_class_pairs(4, 32, seed=0)
    validation = rendered_class_pairs(2, 32, seed=1)
    given = train_referee(data.targets, data.classes, validation.inputs, validation.classes, CLASSIFY, seed=0)
    assert build_judge("colour", data, validation, given, CLASSIFY, 0) is None
    assert build_judge("recognition", data, validation, given, CLASSIFY, 0) is given  # select_every's, reused
    trained = build_judge("recognition", data, validation, None, CLASSIFY, 0)
    assert trained is not None and trained.class_names == tuple(sorted(set(data.classes)))
    aligned = PairData(validation.inputs, validation.targets, validation.classes,
                       torch.ones(len(validation.classes), dtype=torch.bool), validation.pool_images, validation.input_pool)
    assert build_judge("recognition", data, aligned, None, CLASSIFY, 0) is None  # Colour-SSIM scores every class
    # a checkpoint written with one signal is not resumed with the other: the early-stopping history differs
    settings = dict(SETTINGS, **CLASS_GAN, iterations=6)
    assert checkpoint_keys(settings, RUN, "v2t", "all", data, judged=True)["params"] != \
        checkpoint_keys(settings, RUN, "v2t", "all", data)["params"]


def test_a_class_settles_under_the_judge_only_from_chance_or_half_its_real_images_score_up():
    data = rendered_class_pairs(4, 32, seed=0)
    judge = train_referee(data.targets, data.classes, data.inputs, data.classes, JUDGE_CLASSIFY, seed=0)
    aligned = torch.tensor([name == "felt" for name in data.classes])  # felt has aligned pairs: Colour-SSIM, no floor
    validation = PairData(data.inputs, data.targets, data.classes, aligned, data.pool_images, data.input_pool)
    floor = recognition_floor(judge, validation)
    assert set(floor) == {"plain_weave", "corduroy"}
    for name, value in floor.items():
        rows = [i for i, c in enumerate(data.classes) if c == name]
        real = float(judge.recognition(data.targets[rows], [name] * len(rows)).mean())
        assert value == pytest.approx(min(1 / 3, real / 2))
    # black "real" targets: the judge's probabilities for one image sum to 1 over three classes, so some class
    # gets at most 1/3 and its floor is half of that, below chance
    black = torch.zeros_like(data.targets)
    dark = recognition_floor(judge, PairData(data.inputs, black, data.classes, aligned, data.pool_images, data.input_pool))
    probability = {name: float(judge.recognition(black[:1], [name])[0]) for name in dark}
    assert dark == pytest.approx({name: min(1 / 3, p / 2) for name, p in probability.items()})
    assert min(dark.values()) < 1 / 3
