"""class_gan.lr_decay: both learning rates constant, then falling linearly towards 0 over the last share of the
steps (its formula, its off switch, per-direction values, and that the training loop applies it)."""

from __future__ import annotations

import copy

import pytest
import torch

from test_class_gan import batch, CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.translator import TranslatorTraining
from vtgen.stages.train import objective_settings, train_translator


def rates(training: TranslatorTraining) -> tuple[float, float]:
    (g,), (d,) = training.opt_g.param_groups, training.opt_d.param_groups
    return g["lr"], d["lr"]


def test_the_rates_follow_the_linear_decay_over_the_last_share_of_the_steps():
    training = TranslatorTraining(dict(SETTINGS, **dict(CLASS_GAN, d_lr_ratio=2.0), lr_decay=0.5), "cpu", num_classes=2)
    lr = SETTINGS["lr"]
    # T = 8, f = 0.5: lr_t = lr * min(1, (8 - t) / 4)
    for step, scale in ((0, 1.0), (3, 1.0), (4, 1.0), (5, 0.75), (6, 0.5), (7, 0.25)):
        training.schedule_learning_rate(step, 8)
        g, d = rates(training)
        assert g == pytest.approx(lr * scale, rel=1e-12) and d == pytest.approx(2 * lr * scale, rel=1e-12)
    training.schedule_learning_rate(2, 8)  # a function of the step alone: going back restores the rate
    assert rates(training) == pytest.approx((lr, 2 * lr), rel=1e-12)


def test_lr_decay_0_leaves_the_rates_and_the_step_bit_for_bit():
    def stepped(settings):
        torch.manual_seed(0)
        training = TranslatorTraining(settings, "cpu", num_classes=2)
        for t in range(2):
            training.schedule_learning_rate(t, 2)
            training.step(*batch(t))
        assert rates(training) == (SETTINGS["lr"], SETTINGS["lr"])
        return [p.detach().clone() for p in (*training.generator.parameters(), *training.discriminator.parameters())]

    without, zero = stepped(dict(SETTINGS, **CLASS_GAN)), stepped(dict(SETTINGS, **CLASS_GAN, lr_decay=0.0))
    assert all(torch.equal(a, b) for a, b in zip(without, zero))
    # on: the last step's rates are smaller, so the weights differ
    torch.manual_seed(0)
    on = TranslatorTraining(dict(SETTINGS, **CLASS_GAN, lr_decay=1.0), "cpu", num_classes=2)
    for t in range(2):
        on.schedule_learning_rate(t, 2)
        on.step(*batch(t))
    assert rates(on) == pytest.approx((SETTINGS["lr"] / 2, SETTINGS["lr"] / 2), rel=1e-12)
    assert any(not torch.equal(a, b) for a, b in zip(without, on.generator.parameters()))
    # pix2pix ignores the key
    pix2pix = TranslatorTraining(dict(SETTINGS, lr_decay=1.0), "cpu")
    pix2pix.schedule_learning_rate(1, 2)
    assert rates(pix2pix) == (SETTINGS["lr"], SETTINGS["lr"])


def test_off_adds_no_settings_key_and_a_value_may_be_given_per_direction(default_params):
    from vtgen.io.params import ParamsError, validate_params
    params = copy.deepcopy(default_params)
    assert params["translation"]["class_gan"]["lr_decay"] == 0.0
    plain = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")
    plain_t2v = objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v")  # the defaults differ by direction
    assert "lr_decay" not in plain  # so the default's checkpoint keys are those of the code before the switch
    params["translation"]["class_gan"]["lr_decay"] = {"v2t": 0.5, "t2v": 0.0}
    validate_params(params)
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "v2t")["lr_decay"] == 0.5
    assert objective_settings(dict(SETTINGS), params["translation"], "class_gan", "t2v") == plain_t2v
    params["translation"]["class_gan"]["lr_decay"] = 1.5
    with pytest.raises(ParamsError, match=r"translation\.class_gan\.lr_decay"):
        validate_params(params)


def test_the_training_loop_decays_the_rates_to_the_last_steps_and_checkpoints_them(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    base = dict(SETTINGS, **CLASS_GAN, iterations=4)
    run = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=4, resume=False, log_every=2, seed=0)
    on = train_translator(data, dict(base, lr_decay=1.0), run, "v2t", "all", checkpoint_dir=tmp_path / "on",
                          progress=False)
    off = train_translator(data, base, run, "v2t", "all", checkpoint_dir=tmp_path / "off", progress=False)
    saved = torch.load(tmp_path / "on" / "last.pt", weights_only=False)
    # the last of T = 4 steps ran at lr * (4 - 3) / 4
    assert saved["opt_g"]["param_groups"][0]["lr"] == pytest.approx(SETTINGS["lr"] / 4, rel=1e-12)
    assert saved["opt_d"]["param_groups"][0]["lr"] == pytest.approx(SETTINGS["lr"] / 4, rel=1e-12)
    assert torch.load(tmp_path / "off" / "last.pt", weights_only=False)["opt_g"]["param_groups"][0]["lr"] == SETTINGS["lr"]
    assert any(not torch.equal(a, b) for a, b in zip(on.generator.parameters(), off.generator.parameters()))
