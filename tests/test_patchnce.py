"""PatchNCE (class_gan.nce): the loss on known inputs, the generator's encoder it reads, and the step with it."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from vtgen.core.models import UNetGenerator
from vtgen.core.patchnce import patch_nce_loss, PatchProjection
from vtgen.core.translator import TranslatorTraining

SETTINGS = {"size": 32, "ngf": 8, "ndf": 8, "kernel": 4, "discriminator": "patch", "patch_layers": 2,
            "gan_loss": "bce", "l1_weight": 100.0, "optimizer": "adam", "lr": 2e-4, "betas": [0.5, 0.999],
            "batch_size": 4, "iterations": 4, "objective": "class_gan", "r1": 0.1, "diffaugment": True,
            "mode_seeking": 1.0, "mode_seeking_pool": 1, "statistics": 0.0, "class_guidance": 0.0, "semantic": 0.0,
            "skips": None, "d_lr_ratio": 1.0, "latent": 8, "upsample": "transpose"}


def direct_nce(query: torch.Tensor, key: torch.Tensor, projection: PatchProjection, level: int, where: torch.Tensor,
               temperature: float) -> float:
    """InfoNCE written out per image and per query patch (Park et al. 2020, eq. 3)."""
    total, count = 0.0, 0
    for q_map, k_map in zip(query, key):
        q = [projection(level, q_map[:, int(p) // q_map.shape[2], int(p) % q_map.shape[2]]) for p in where]
        k = [projection(level, k_map[:, int(p) // k_map.shape[2], int(p) % k_map.shape[2]]) for p in where]
        for i in range(len(where)):
            scores = [float(q[i] @ k[j]) / temperature for j in range(len(where))]
            total += -scores[i] + math.log(sum(math.exp(s) for s in scores))
            count += 1
    return total / count


def test_patch_nce_is_the_infonce_of_each_output_patch_against_the_input_patches_of_its_image():
    torch.manual_seed(0)
    projection = PatchProjection([4, 6], dim=5)
    queries = [torch.randn(2, 4, 4, 4), torch.randn(2, 6, 2, 2)]
    keys = [torch.randn(2, 4, 4, 4), torch.randn(2, 6, 2, 2)]
    torch.manual_seed(3)
    loss = float(patch_nce_loss(queries, keys, projection, patches=5, temperature=0.2).detach())
    torch.manual_seed(3)  # the same locations: 5 of 16 at level 0, all 4 at level 1
    where = [torch.randperm(16)[:5], torch.randperm(4)[:4]]
    with torch.no_grad():
        expected = sum(direct_nce(queries[lv], keys[lv], projection, lv, where[lv], 0.2) for lv in range(2)) / 2
    assert loss == pytest.approx(expected, rel=1e-5)


def test_patch_nce_is_lower_when_the_output_keeps_the_inputs_structure():
    torch.manual_seed(0)
    projection = PatchProjection([8], dim=16)
    key = torch.randn(3, 8, 8, 8)
    with torch.no_grad():
        kept = float(patch_nce_loss([key.clone()], [key], projection, patches=64))
        moved = float(patch_nce_loss([torch.roll(key, shifts=(3, 2), dims=(2, 3))], [key], projection, patches=64))
    assert kept < 0.5 * moved
    with pytest.raises(ValueError, match="one key map per query map"):
        patch_nce_loss([key], [], projection)


def test_encode_gives_the_encoder_outputs_of_a_zero_code_and_keeps_the_running_statistics():
    torch.manual_seed(0)
    generator = UNetGenerator(32, 8, in_channels=3, latent=4).train()
    x = torch.rand(4, 3, 32, 32) * 2 - 1
    before = {k: v.clone() for k, v in generator.state_dict().items()}
    maps = generator.encode(x, (0, 2))
    assert all(torch.equal(v, generator.state_dict()[k]) for k, v in before.items())
    h = torch.cat([x, torch.zeros(4, 4, 32, 32)], dim=1)
    outputs = []
    for block in generator.encoder[:3]:
        h = block(h)
        outputs.append(h)
    assert torch.allclose(maps[0], outputs[0]) and torch.allclose(maps[1], outputs[2])
    assert [m.shape[-1] for m in maps] == [16, 4]


def weights(training):
    return [p.detach().clone() for p in (*training.generator.parameters(), *training.discriminator.parameters())]


def batch():
    g = torch.Generator().manual_seed(0)
    return torch.rand(4, 3, 32, 32, generator=g) * 2 - 1, torch.rand(4, 3, 32, 32, generator=g) * 2 - 1, \
        torch.tensor([0, 0, 1, 1])


def test_nce_weight_0_is_the_step_without_it_and_a_weight_trains_the_projection_with_the_generator():
    torch.manual_seed(0)
    plain = TranslatorTraining(dict(SETTINGS), "cpu", num_classes=2)
    plain.step(*batch())
    torch.manual_seed(0)
    off = TranslatorTraining(dict(SETTINGS, nce=0.0), "cpu", num_classes=2)
    off.step(*batch())
    assert all(torch.equal(a, b) for a, b in zip(weights(plain), weights(off)))
    assert off.nce_projection is None and "nce_projection" not in off.state_dict()
    torch.manual_seed(0)
    on = TranslatorTraining(dict(SETTINGS, nce=1.0), "cpu", num_classes=2)
    heads = [p.detach().clone() for p in on.nce_projection.parameters()]
    on.step(*batch())
    assert any(not torch.equal(a, b) for a, b in zip(heads, on.nce_projection.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(weights(on)[:len(weights(off))], weights(off)))
    copy = TranslatorTraining(dict(SETTINGS, nce=1.0), "cpu", num_classes=2)
    copy.load_state_dict(on.state_dict())
    assert all(torch.equal(a, b) for a, b in zip(copy.nce_projection.parameters(), on.nce_projection.parameters()))


def test_the_nce_term_makes_outputs_keep_their_inputs_layout():
    """G alone (D's learning rate 0) under PatchNCE only: after training, an output's encoder features match
    its own input's at the same place better than another input's (the contrastive task is learnt)."""
    torch.manual_seed(0)
    settings = dict(SETTINGS, nce=1.0, latent=0, mode_seeking=0.0, lr=1e-3)
    training = TranslatorTraining(settings, "cpu", num_classes=2)
    training.opt_d = torch.optim.SGD(training.discriminator.parameters(), lr=0.0)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(4, 3, 32, 32, generator=g) * 2 - 1
    y = torch.rand(4, 3, 32, 32, generator=g) * 2 - 1

    def nce_now() -> float:
        torch.manual_seed(9)
        fake = training.generator(x)
        keys = training.generator.encode(x, training.nce_levels)
        queries = training.generator.encode(fake, training.nce_levels)
        return float(patch_nce_loss(queries, keys, training.nce_projection).detach())

    start = nce_now()
    for _ in range(30):
        training.step(x, y, torch.tensor([0, 0, 1, 1]))
    assert nce_now() < 0.7 * start
    assert F.l1_loss(training.generator(x), y) > 0  # no pixel target was used: only structure is asked for


def test_nce_is_set_per_direction_and_each_model_trains_with_its_own_weight():
    from vtgen.stages.train import objective_settings

    translation = {"preset": "fast", "class_gan": {"r1": 0.1, "nce": {"v2t": 0.3, "t2v": 0.0}, "skips": "all"}}
    assert objective_settings({"batch_size": 4}, translation, "class_gan", "v2t")["nce"] == 0.3
    assert objective_settings({"batch_size": 4}, translation, "class_gan", "t2v")["nce"] == 0.0
    assert translation["class_gan"]["nce"] == {"v2t": 0.3, "t2v": 0.0}  # the params are not changed
    with pytest.raises(ValueError, match="class_gan.nce is given per direction"):
        objective_settings({"batch_size": 4}, translation, "class_gan")
