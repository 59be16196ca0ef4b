"""Stability at the edges: each edge case trains to a finite model or stops clearly; nothing broken is saved."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch
from torch import nn

import vtgen.studies.stability as stability
from conftest import tiny_params, write_image
from vtgen.core.gan import to_model_range
from vtgen.core.models import GlobalDiscriminator, PatchDiscriminator, UNetGenerator
from vtgen.studies.stability import EDGE_CASES, run_case, write_stability
from vtgen.stages.train import run_train, TrainingDiverged

ITERATIONS = 2  # per case; enough to take every optimiser step path, cheap on 2 shared cores
# bf16 against fp32 after ITERATIONS steps from one seed, eval-mode outputs on [-1, 1] (fast preset, this CPU):
# measured max |diff| 5.0e-4 and mean |diff| / mean |fp32 output| 0.8% (1 step: 2.8e-4; 4 steps: 6.8e-4, 1.1%;
# 20 steps: 1.5e-2, 6.9%, as the two trajectories drift apart). Bounds: about 10x and 6x the measured values.
BF16_MAX_ABS = 5e-3
BF16_REL = 0.05
STOP_MESSAGES = {
    "size_min_deep_patchgan": r"size 16 is too small for patch_layers=3",
    "size_below_min": r"size must be a power of two >= 16, got 8",
    "batch1_batchnorm_1x1": r"GlobalDiscriminator: .*1 x 1 map.*use batch_size >= 2",
    "lr_absurd": r"TrainingDiverged: v2t/all: diverged at step \d+: generator weight norm .* outside its range.*"
                 r"lower presets\.fast\.lr \(now 1000\)",
}


@pytest.fixture(scope="module")
def results():
    """run_case results on the default params (1 thread: the cores are shared), computed once per case."""
    import yaml

    from conftest import REPO

    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["translation"].update(device="cpu", threads=1)
    cache: dict = {}

    def get(name: str):
        if name not in cache:
            cache[name] = run_case(next(c for c in EDGE_CASES if c.name == name), params, ITERATIONS)
        return cache[name]

    return get


def all_finite(module: nn.Module) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in module.state_dict().values() if t.is_floating_point())


@pytest.mark.parametrize("name", [case.name for case in EDGE_CASES])
@pytest.mark.slow
def test_edge_case_trains_to_a_finite_model_or_stops_clearly(results, name):
    case = next(c for c in EDGE_CASES if c.name == name)
    result = results(name)
    row = result.row
    assert row["outcome"] == case.expect, row["message"]
    assert row["checkpoint"] in ("none", "finite")  # never a non-finite checkpoint
    if case.expect == "finite":
        assert row["steps"] == min(ITERATIONS, case.max_iterations or ITERATIONS)
        assert all_finite(result.generator)
        result.generator.eval()
        with torch.no_grad():
            out = result.generator(to_model_range(result.data.inputs[:2]))
        assert torch.isfinite(out).all() and out.abs().max() <= 1.0
        assert np.isfinite([row["loss_d"], row["loss_g_gan"], row["loss_g_l1"], row["max_abs_weight"]]).all()
    else:
        assert result.generator is None
        assert pd.Series([row["message"]]).str.contains(STOP_MESSAGES[name], regex=True).all(), row["message"]


def test_bf16_and_fp32_from_the_same_seed_give_close_finite_outputs(results):
    result = results("bf16_vs_fp32")
    assert result.reference is not None and all_finite(result.generator) and all_finite(result.reference)
    row = result.row
    # autocast keeps fp32 weights and optimiser state; only activations are rounded to bf16's 8-bit mantissa
    # (relative rounding error 2**-9 per operation), so two steps cannot drift far. Non-zero: bf16 was really used.
    assert 0 < row["bf16_max_abs_diff"] < BF16_MAX_ABS, row["bf16_max_abs_diff"]
    assert row["bf16_mean_abs_diff"] <= row["bf16_max_abs_diff"]
    assert row["bf16_rel_diff"] < BF16_REL, row["bf16_rel_diff"]


def test_batchnorm_on_a_1x1_map_at_batch_1_is_refused_with_the_setting_named():
    torch.manual_seed(0)
    with pytest.raises(ValueError, match=r"GlobalDiscriminator: .*use batch_size >= 2 or size >= 32"):
        GlobalDiscriminator(16, ndf=2, kernel=5).train()(torch.zeros(1, 6, 16, 16))
    with pytest.raises(ValueError, match=r"PatchDiscriminator: .*fewer patch_layers \(now 4\)"):
        PatchDiscriminator(ndf=2, layers=4, kernel=5).train()(torch.zeros(1, 6, 16, 16))
    assert GlobalDiscriminator(16, ndf=2, kernel=5).train()(torch.zeros(2, 6, 16, 16)).shape == (2, 1)
    assert GlobalDiscriminator(16, ndf=2, kernel=5).eval()(torch.zeros(1, 6, 16, 16)).shape == (1, 1)
    assert PatchDiscriminator(ndf=2, layers=3, kernel=4).train()(torch.zeros(1, 6, 32, 32)).shape == (1, 1, 2, 2)
    # the generator has no BatchNorm at its 1 x 1 bottleneck (pix2pix), so batch 1 trains at the minimum size
    assert torch.isfinite(UNetGenerator(16, ngf=2).train()(torch.zeros(1, 3, 16, 16))).all()


def test_an_error_from_inside_torch_counts_as_a_crash_not_a_clear_stop():
    with pytest.raises(ValueError) as raw:
        nn.BatchNorm2d(2).train()(torch.zeros(1, 2, 1, 1))
    assert not stability._raised_by_vtgen(raw.value)
    with pytest.raises(ValueError) as ours:
        UNetGenerator(8)
    assert stability._raised_by_vtgen(ours.value)


def pairs_folder(root):
    """The pairs stage's tables for two classes of 3 aligned 32 px training pairs, tiles written under ``root``."""
    rng = np.random.default_rng(0)
    rows, tiles = [], []
    for cls in ("a", "b"):
        for i in range(3):
            for modality in ("visual", "tactile"):
                path = f"tiles/{modality}/{cls}/{i}.png"
                write_image(root / path, rng.integers(0, 256, (32, 32, 3), dtype=np.uint8))
                tiles.append({"path": path, "class": cls, "modality": modality, "source": f"{cls}/{i}",
                              "group": f"{cls}/{i}", "split": "train"})
            rows.append({"direction": "v2t", "split": "train", "class": cls, "input_path": f"tiles/visual/{cls}/{i}.png",
                         "target_path": f"tiles/tactile/{cls}/{i}.png", "input_source": f"{cls}/{i}",
                         "target_source": f"{cls}/{i}", "aligned": True, "pair_kind": "pixel"})
    (root / "pairs").mkdir()
    pd.DataFrame(rows).to_parquet(root / "pairs/v2t.parquet")
    pd.DataFrame(tiles).to_parquet(root / "pairs/splits.parquet")


@pytest.mark.slow
def test_run_train_never_writes_a_diverged_model(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    pairs_folder(tmp_path)
    params = tiny_params(translation={"threads": 1, "checkpoint_every": 2})
    params["presets"]["fast"].update(iterations=6, lr=0.1)
    run_train(params, "v2t", "all", "pairs", "models/high", "ckpt/high", progress=False)  # lr 1e-1: still finite
    saved = torch.load(tmp_path / "models/high/generator.pt", weights_only=False)
    assert all(torch.isfinite(t).all() for t in saved["state_dict"].values() if t.is_floating_point())

    params["presets"]["fast"].update(lr=1e3)  # finite weights, but exploding: stopped at the first logged window
    with pytest.raises(TrainingDiverged, match=r"diverged at step 2: generator weight norm .*lower presets.fast.lr"):
        run_train(params, "v2t", "all", "pairs", "models/absurd", "ckpt/absurd", progress=False)
    assert not (tmp_path / "models/absurd").exists()  # no generator.pt, no half-written folder
    assert not list((tmp_path / "models").glob(".absurd*"))
    checkpoint = tmp_path / "ckpt/absurd/v2t/all/last.pt"
    if checkpoint.exists():  # only a checkpoint from before the divergence, and finite (none at lr 1e3)
        state = torch.load(checkpoint, weights_only=False)
        assert all(torch.isfinite(t).all() for t in state["generator"].values() if t.is_floating_point())


def test_write_stability_counts_outcomes_and_refuses_a_broken_table(tmp_path):
    table = pd.DataFrame([
        {"case": "a", "expected": "finite", "outcome": "finite", "message": ""},
        {"case": "b", "expected": "stopped", "outcome": "stopped", "message": "ValueError: size"},
        {"case": "c", "expected": "finite", "outcome": "stopped", "message": "TrainingDiverged: step 3"},
    ])
    summary = write_stability(table, tmp_path / "out")
    assert summary == {"cases": 3, "finite": 1, "stopped": 2, "crashed": 0, "broken": 0, "unexpected": ["c"]}
    assert json.loads((tmp_path / "out/summary.json").read_text()) == summary
    assert len(pd.read_csv(tmp_path / "out/stability.csv")) == 3
    broken = pd.concat([table, pd.DataFrame([{"case": "d", "expected": "finite", "outcome": "broken",
                                              "message": "non-finite model"}])])
    with pytest.raises(RuntimeError, match="d broken"):
        write_stability(broken, tmp_path / "again")
    assert not (tmp_path / "again").exists()


def test_run_stability_gives_one_row_per_case(monkeypatch):
    cheap = [c for c in EDGE_CASES if c.name in ("size_below_min", "width_min")]
    monkeypatch.setattr(stability, "EDGE_CASES", cheap)
    params = tiny_params(translation={"threads": 1})
    table = stability.run_stability(params, iterations=1)
    assert list(table.columns) == stability.COLUMNS
    assert list(table["case"]) == ["size_below_min", "width_min"] and list(table["outcome"]) == ["stopped", "finite"]
