"""class_gan.ema: the moving average of the generator's weights that a run yields (its formula, its off switch,
resume, and that the training loop hands it on)."""

from __future__ import annotations

import torch

from test_class_gan import batch, CLASS_GAN, rendered_class_pairs, SETTINGS
from vtgen.core.translator import TranslatorTraining
from vtgen.stages.train import objective_settings, train_translator

RUN = dict(device="cpu", precision="fp32", threads=1, checkpoint_every=3, resume=True, log_every=3, seed=0)


def state(module: torch.nn.Module) -> dict:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def test_the_average_follows_the_formula_with_its_warm_up():
    torch.manual_seed(0)
    training = TranslatorTraining(dict(SETTINGS, **CLASS_GAN, ema=0.9), "cpu", num_classes=2)
    assert torch.equal(torch.cat([p.flatten() for p in training.average.parameters()]),
                       torch.cat([p.flatten() for p in training.generator.parameters()]))
    expected = state(training.average)
    for t in (1, 2, 3):
        training.step(*batch(t))
        live = state(training.generator)
        decay = min(0.9, (1 + t) / (10 + t))  # 0.18, 0.25, 0.31: the warm-up binds in these first steps
        for key, value in expected.items():
            expected[key] = decay * value + (1 - decay) * live[key] if value.is_floating_point() else live[key]
        averaged = state(training.average)
        for key in expected:
            torch.testing.assert_close(averaged[key], expected[key], rtol=1e-6, atol=1e-7)
    # not the live weights, and no gradient reaches the average
    assert any(not torch.equal(averaged[k], live[k]) for k in live if live[k].is_floating_point())
    assert not any(p.requires_grad for p in training.average.parameters())
    assert training.output_generator is training.average


def test_ema_0_is_the_step_without_an_average_bit_for_bit():
    def stepped(settings):
        torch.manual_seed(0)
        training = TranslatorTraining(settings, "cpu", num_classes=2)
        for t in range(2):
            training.step(*batch(t))
        assert training.average is None and training.output_generator is training.generator
        assert "average" not in training.state_dict()
        return state(training.generator) | {f"d.{k}": v for k, v in state(training.discriminator).items()}

    without, zero = stepped(dict(SETTINGS, **CLASS_GAN)), stepped(dict(SETTINGS, **CLASS_GAN, ema=0.0))
    assert without.keys() == zero.keys() and all(torch.equal(without[k], zero[k]) for k in without)
    # pix2pix ignores the key: its step has no average
    assert TranslatorTraining(dict(SETTINGS, ema=0.9), "cpu").average is None


def test_a_resumed_run_yields_the_same_average_and_the_run_returns_it(tmp_path):
    data = rendered_class_pairs(4, 32, seed=0)
    settings = objective_settings(dict(SETTINGS, patch_layers=2, iterations=9),
                                  {"preset": "t", "class_gan": dict({k: v for k, v in CLASS_GAN.items()
                                                                     if k != "objective"}, ema=0.99)}, "class_gan")
    full = train_translator(data, settings, RUN, "v2t", "all", checkpoint_dir=tmp_path / "full", progress=False)
    train_translator(data, dict(settings, iterations=6), RUN, "v2t", "all", checkpoint_dir=tmp_path / "split",
                     progress=False)
    resumed = train_translator(data, settings, RUN, "v2t", "all", checkpoint_dir=tmp_path / "split", progress=False)
    assert resumed.resumed_from == 6
    a, b = state(full.generator), state(resumed.generator)
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    saved = torch.load(tmp_path / "full" / "last.pt", weights_only=False)
    assert saved["average"]["updates"] == 9
    # the run yields the average, not the live generator the checkpoint also holds
    assert all(torch.equal(a[k], saved["average"]["generator"][k]) for k in a)
    assert any(not torch.equal(a[k], saved["generator"][k]) for k in a if a[k].is_floating_point())
