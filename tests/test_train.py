"""Training loop: learning, both discriminators, resume, divergence, determinism, data handling."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest
import torch

import vtgen.stages.train as train_module
from conftest import pair_tables, TINY_MODEL, write_image
from vtgen.core.gan import random_positioning, to_model_range
from vtgen.stages.train import BatchStream, draw_batch, load_pair_data, PairData, prepare_batch, run_train, SpeedChoices, train_translator, TrainingDiverged
from vtgen.io.images import read_tiles

SETTINGS = dict(TINY_MODEL, gan_loss="bce", l1_weight=100.0, optimizer="adam", lr=0.0002, betas=[0.5, 0.999],
                noise=True)
RUN = dict(device="cpu", precision="fp32", threads=2, checkpoint_every=4, resume=True, log_every=2, seed=0)


def texture_pairs(n: int = 6, size: int = 32, seed: int = 0) -> PairData:
    """Aligned pairs whose target is a fixed function of the input (colour swap and inversion)."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (n, 3, size // 4, size // 4), dtype=np.uint8)
    inputs = torch.from_numpy(base).repeat_interleave(4, 2).repeat_interleave(4, 3)
    targets = 255 - inputs[:, [2, 0, 1]]
    classes = ["a", "b"] * (n // 2)
    return PairData(inputs, targets, classes, torch.ones(n, dtype=torch.bool), inputs.clone(),
                    {c: torch.tensor([i for i, k in enumerate(classes) if k == c]) for c in ("a", "b")})


def weights(generator: torch.nn.Module) -> dict:
    return {k: v.clone() for k, v in generator.state_dict().items()}


def same_weights(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_generator_overfits_a_single_aligned_pair():
    data = texture_pairs(n=1)
    settings = dict(SETTINGS, iterations=150, batch_size=1, noise=False, lr=0.002)
    result = train_translator(data, settings, dict(RUN, checkpoint_every=75), "v2t", "all", progress=False,
                              validation=data)
    first, last = result.history[0]["loss_g_l1"], result.history[-1]["loss_g_l1"]
    assert last < 0.25 * first
    validated = [row["val_l1"] for row in result.history if "val_l1" in row]
    assert len(validated) == 2 and validated[1] < validated[0]  # eval-mode error on the pair falls too
    generator = result.generator.train()  # batch statistics, as during training
    with torch.no_grad():
        output = generator(to_model_range(data.inputs))
    error = (output - to_model_range(data.targets)).abs().mean().item()
    assert error < 0.15, error  # on [-1, 1]: under 8% of the range, from about 0.5 for the untrained network


@pytest.mark.parametrize("kind", ["global", "patch"])
def test_both_discriminators_train(kind):
    settings = dict(SETTINGS, discriminator=kind, kernel=5 if kind == "global" else 4, iterations=60, batch_size=4)
    result = train_translator(texture_pairs(), settings, dict(RUN, log_every=10, checkpoint_every=1000), "v2t", "all",
                              progress=False)
    losses = pd.DataFrame(result.history)
    assert np.isfinite(losses[["loss_d", "loss_g_gan", "loss_g_l1"]].to_numpy()).all()
    # the discriminator learns to tell real from fake: its loss falls from chance, log 2 = 0.693
    assert losses["loss_d"].iloc[-1] < 0.9 * min(losses["loss_d"].iloc[0], 0.693)
    assert losses["loss_g_l1"].iloc[-1] < losses["loss_g_l1"].iloc[0]


def test_training_is_deterministic_on_cpu(tmp_path):
    runs = [train_translator(texture_pairs(), dict(SETTINGS, iterations=8), RUN, "v2t", "all", progress=False)
            for _ in range(2)]
    assert same_weights(weights(runs[0].generator), weights(runs[1].generator))
    other = train_translator(texture_pairs(), dict(SETTINGS, iterations=8), dict(RUN, seed=1), "v2t", "all",
                             progress=False)
    assert not same_weights(weights(runs[0].generator), weights(other.generator))


def test_resume_gives_the_same_weights_as_an_uninterrupted_run(tmp_path, capsys):
    val = texture_pairs(seed=3)
    full = train_translator(texture_pairs(), dict(SETTINGS, iterations=12), RUN, "v2t", "all",
                            checkpoint_dir=tmp_path / "full", progress=False, validation=val)
    train_translator(texture_pairs(), dict(SETTINGS, iterations=8), RUN, "v2t", "all",
                     checkpoint_dir=tmp_path / "split", progress=False, validation=val)
    resumed = train_translator(texture_pairs(), dict(SETTINGS, iterations=12), RUN, "v2t", "all",
                               checkpoint_dir=tmp_path / "split", progress=False, validation=val)
    assert "resuming from step 8" in capsys.readouterr().out
    assert resumed.resumed_from == 8 and resumed.steps == 12
    assert same_weights(weights(full.generator), weights(resumed.generator))
    assert [row["step"] for row in full.history if "val_l1" in row] == [4, 8, 12]  # validated at each checkpoint
    strip = [{k: v for k, v in row.items() if k != "images_per_s"} for row in full.history]
    assert strip == [{k: v for k, v in row.items() if k != "images_per_s"} for row in resumed.history]


def test_a_checkpoint_of_another_configuration_is_not_resumed(tmp_path, capsys):
    train_translator(texture_pairs(), dict(SETTINGS, iterations=4), RUN, "v2t", "all",
                     checkpoint_dir=tmp_path, progress=False)
    result = train_translator(texture_pairs(), dict(SETTINGS, iterations=4, lr=0.001), RUN, "v2t", "all",
                              checkpoint_dir=tmp_path, progress=False)
    assert "another configuration" in capsys.readouterr().out
    assert result.resumed_from == 0
    changed_data = train_translator(texture_pairs(seed=5), dict(SETTINGS, iterations=4, lr=0.001), RUN, "v2t",
                                    "all", checkpoint_dir=tmp_path, progress=False)
    assert changed_data.resumed_from == 0


def test_a_non_finite_loss_stops_training_and_names_the_step(tmp_path, monkeypatch):
    real_loss = train_module.adversarial_loss
    calls = {"n": 0}

    def poisoned(logits, real, kind="bce"):
        calls["n"] += 1  # three calls per step: D real, D fake, G
        loss = real_loss(logits, real, kind)
        return loss * float("nan") if calls["n"] > 3 * 5 else loss

    monkeypatch.setattr(train_module, "adversarial_loss", poisoned)
    with pytest.raises(TrainingDiverged, match=r"non-finite loss at step 6.*last good checkpoint: .*step 4\)"):
        train_translator(texture_pairs(), dict(SETTINGS, iterations=12), RUN, "v2t", "all",
                         checkpoint_dir=tmp_path, progress=False)
    saved = torch.load(tmp_path / "last.pt", weights_only=False)
    assert saved["step"] == 4
    assert all(torch.isfinite(t).all() for t in saved["generator"].values() if t.is_floating_point())


def test_bf16_training_gives_finite_losses():
    result = train_translator(texture_pairs(), dict(SETTINGS, iterations=6), dict(RUN, precision="bf16"), "v2t",
                              "all", progress=False)
    assert np.isfinite(pd.DataFrame(result.history)[["loss_d", "loss_g_gan", "loss_g_l1"]].to_numpy()).all()


def test_unaligned_pairs_draw_a_fresh_input_of_the_same_class():
    data = texture_pairs(n=6)
    data.aligned[:] = False
    data.pool_images = torch.arange(6, dtype=torch.uint8).view(6, 1, 1, 1).expand(6, 3, 32, 32).clone()
    generator = torch.Generator().manual_seed(0)
    seen = {"a": set(), "b": set()}
    for _ in range(40):
        inputs, targets = draw_batch(data, 2, generator)
        for image, target in zip(inputs, targets):
            row = next(i for i in range(6) if torch.equal(data.targets[i], target))
            seen[data.classes[row]].add(int(image[0, 0, 0]))
    assert seen == {"a": {0, 2, 4}, "b": {1, 3, 5}}  # every input of the class, never one of another class


def test_read_tiles_resizes_and_refuses_non_rgb(tmp_path):
    rng = np.random.default_rng(0)
    write_image(tmp_path / "a.png", rng.integers(0, 256, (64, 64, 3), dtype=np.uint8))
    assert read_tiles(["a.png"], 32, tmp_path).shape == (1, 3, 32, 32)
    assert read_tiles(["a.png"], 64, tmp_path).dtype == torch.uint8
    write_image(tmp_path / "g.png", rng.integers(0, 256, (32, 32), dtype=np.uint8))
    with pytest.raises(ValueError, match="g.png: tile is L"):
        read_tiles(["g.png"], 32, tmp_path)


def test_load_pair_data_keeps_the_training_split_of_the_scope(tmp_path):
    pairs, splits = pair_tables(tmp_path)
    data = load_pair_data(pairs, splits, "v2t", "all", 32, tmp_path)
    assert len(data.targets) == 6 and set(data.classes) == {"a", "b"}
    one = load_pair_data(pairs, splits, "v2t", "b", 32, tmp_path)
    assert one.classes == ["b"] * 3 and len(one.pool_images) == 3
    with pytest.raises(ValueError, match="class 'zzz' has no v2t pairs"):
        load_pair_data(pairs, splits, "v2t", "zzz", 32, tmp_path)


def test_run_train_writes_generator_summary_and_loss_log(tmp_path, monkeypatch):
    from conftest import tiny_params

    monkeypatch.chdir(tmp_path)
    pairs, splits = pair_tables(tmp_path)
    (tmp_path / "pairs").mkdir()
    pairs.to_parquet(tmp_path / "pairs/v2t.parquet")
    splits.to_parquet(tmp_path / "pairs/splits.parquet")
    summary = run_train(tiny_params(), "v2t", "all", "pairs", "models/v2t/all", "ckpt", progress=False)
    out = tmp_path / "models/v2t/all"
    assert {p.name for p in out.iterdir()} == {"generator.pt", "train.json", "dvclive"}
    assert summary["steps"] == 10 and summary["training_pairs"] == 6
    logged = pd.read_csv(out / "dvclive/plots/metrics/train/loss_g_l1.tsv", sep="\t")
    assert list(logged["step"]) == [2, 4, 5, 6, 8, 10]  # every log_every (2) steps and at each checkpoint (5)
    assert (tmp_path / "ckpt/v2t/all/last.pt").is_file()
    with pytest.raises(ValueError, match="not listed in translation.scope"):
        run_train(tiny_params(), "v2t", "a", "pairs", "models/v2t/a", "ckpt", progress=False)


# --- speed choices: each must leave training semantics intact -------------------------------------------------

PLAIN = SpeedChoices(fused_optimizer=False, freeze_discriminator=False, channels_last=False, prefetch=False)


def mixed_pairs() -> PairData:
    """Half the pairs unaligned, so a batch draw also redraws inputs from the class pools."""
    data = texture_pairs(n=6)
    data.aligned[::2] = False
    return data


def test_prepare_batch_draws_what_the_plain_loop_drew():
    data, a, b = mixed_pairs(), torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    for _ in range(5):
        inputs, targets = draw_batch(data, 3, a)
        expected = random_positioning(to_model_range(inputs), to_model_range(targets), a)
        got = prepare_batch(data, 3, True, b)
        assert all(torch.equal(e, g) for e, g in zip(expected, got))
    assert torch.equal(a.get_state(), b.get_state())


@pytest.mark.parametrize("noise", [False, True])
def test_prefetch_keeps_the_batch_order_and_sampler_state_of_the_sequential_draw(noise):
    data = mixed_pairs()
    sequential = BatchStream(data, 3, noise, torch.Generator().manual_seed(3))
    prefetched = BatchStream(data, 3, noise, torch.Generator().manual_seed(3), background=True, depth=2)
    try:
        for _ in range(12):
            for a, b in zip(sequential.next(), prefetched.next()):
                assert torch.equal(a, b)
            # the state a checkpoint stores is the one after the batch handed out, not after those prepared ahead
            assert torch.equal(sequential.sampler_state, prefetched.sampler_state)
    finally:
        prefetched.close()
    assert not prefetched._thread.is_alive()


def test_a_failure_on_the_prefetch_thread_reaches_the_training_thread():
    data = mixed_pairs()
    data.input_pool = {}  # an unaligned draw now fails with KeyError on the background thread
    stream = BatchStream(data, 6, False, torch.Generator().manual_seed(0), background=True)
    try:
        with pytest.raises(KeyError):
            stream.next()
    finally:
        stream.close()


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_freezing_the_discriminator_and_prefetching_leave_the_weights_bitwise_equal(precision):
    settings, run = dict(SETTINGS, iterations=8), dict(RUN, precision=precision)
    plain = train_translator(mixed_pairs(), settings, run, "v2t", "all", progress=False, speed=PLAIN)
    for speed in (SpeedChoices(fused_optimizer=False, freeze_discriminator=True),
                  SpeedChoices(fused_optimizer=False, freeze_discriminator=False, prefetch=True)):
        other = train_translator(mixed_pairs(), settings, run, "v2t", "all", progress=False, speed=speed)
        assert same_weights(weights(plain.generator), weights(other.generator)), speed
        assert [r["loss_g_l1"] for r in plain.history] == [r["loss_g_l1"] for r in other.history]


def test_the_fused_optimizer_step_matches_the_plain_step_to_rounding():
    settings = dict(SETTINGS, iterations=6)
    plain = train_translator(texture_pairs(), settings, RUN, "v2t", "all", progress=False, speed=PLAIN)
    fused = train_translator(texture_pairs(), settings, RUN, "v2t", "all", progress=False,
                             speed=dataclasses.replace(PLAIN, fused_optimizer=True))
    for key, value in weights(plain.generator).items():
        assert torch.allclose(value.float(), weights(fused.generator)[key].float(), rtol=1e-3, atol=1e-5), key
    rmsprop = dict(settings, optimizer="rmsprop")
    a = train_translator(texture_pairs(), rmsprop, RUN, "v2t", "all", progress=False, speed=PLAIN)
    b = train_translator(texture_pairs(), rmsprop, RUN, "v2t", "all", progress=False,
                         speed=dataclasses.replace(PLAIN, fused_optimizer=True))
    for key, value in weights(a.generator).items():
        assert torch.allclose(value.float(), weights(b.generator)[key].float(), rtol=1e-3, atol=1e-5), key


def test_channels_last_bf16_training_is_finite_deterministic_and_returns_a_plain_layout_generator():
    speed = SpeedChoices(channels_last=True, prefetch=True)
    run = dict(RUN, precision="bf16")
    results = [train_translator(mixed_pairs(), dict(SETTINGS, iterations=6), run, "v2t", "all", progress=False,
                                speed=speed) for _ in range(2)]
    assert np.isfinite(pd.DataFrame(results[0].history)[["loss_d", "loss_g_gan", "loss_g_l1"]].to_numpy()).all()
    assert same_weights(weights(results[0].generator), weights(results[1].generator))
    assert all(t.is_contiguous() for t in results[0].generator.state_dict().values())
    nchw = train_translator(mixed_pairs(), dict(SETTINGS, iterations=6), run, "v2t", "all", progress=False,
                            speed=dataclasses.replace(speed, channels_last=False))
    l1 = [r["loss_g_l1"] for r in results[0].history], [r["loss_g_l1"] for r in nchw.history]
    assert np.allclose(*l1, rtol=0.05), l1  # same training, up to bf16 rounding in other kernels


def test_a_run_with_prefetch_resumes_exactly(tmp_path):
    settings, speed = dict(SETTINGS, iterations=12), SpeedChoices(prefetch=True)
    full = train_translator(mixed_pairs(), settings, RUN, "v2t", "all", progress=False)
    train_translator(mixed_pairs(), dict(settings, iterations=8), RUN, "v2t", "all",
                     checkpoint_dir=tmp_path, progress=False, speed=speed)
    resumed = train_translator(mixed_pairs(), settings, RUN, "v2t", "all", checkpoint_dir=tmp_path,
                               progress=False, speed=speed)
    assert resumed.resumed_from == 8
    assert same_weights(weights(full.generator), weights(resumed.generator))
