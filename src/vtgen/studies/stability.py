"""Numerical stability at the edges of the parameter space, through the real training loop.

Each entry of :data:`EDGE_CASES` changes the configured preset (resolution, width, batch size,
learning rate, precision) or the data (a class with one pair) and runs
:func:`vtgen.stages.train.train_translator` for a few iterations on structured random pairs held in
memory, with checkpoints in a temporary folder. Every case ends in one of four outcomes:

* ``finite``  - trained; every weight, running statistic, checkpoint and eval-mode output is finite;
* ``stopped`` - refused or stopped by vtgen itself with a clear error (``TrainingDiverged``, or a
  ``ValueError`` naming the setting), and no non-finite checkpoint was written;
* ``crashed`` - an error raised inside torch or another library (an opaque message): a bug;
* ``broken``  - a non-finite model was returned or saved: a bug.
"""

from __future__ import annotations

import json
import tempfile
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import torch

from vtgen.io.params import model_settings
from vtgen.core.gan import to_model_range
from vtgen.core.models import MIN_SIZE, PatchDiscriminator
from vtgen.stages.train import CHECKPOINT_NAME, LOSS_NAMES, PairData, train_translator, TrainingDiverged

OUTCOMES = ("finite", "stopped", "crashed", "broken")
PACKAGE_DIR = Path(__file__).resolve().parents[1]
DEFAULT_PAIRS = 8
LARGEST_SIZE = 1024  # the largest preset size workflow/schemas/params.schema.yaml accepts
COLUMNS = ["case", "probe", "settings", "expected", "outcome", "message", "steps", *LOSS_NAMES, "val_l1",
           "max_abs_weight", "max_abs_running_stat", "checkpoint", "seconds",
           "bf16_max_abs_diff", "bf16_mean_abs_diff", "bf16_rel_diff"]


@dataclass(frozen=True)
class EdgeCase:
    """One probe: ``overrides`` replace keys of the configured preset; ``pairs`` training pairs of one class
    (``aligned`` or redrawn from a pool of the class's inputs); ``max_iterations`` caps expensive cases;
    ``fit_patch_layers`` lowers a PatchGAN's depth to the largest the size allows; ``expect`` is the
    outcome the case is built to reach."""

    name: str
    probe: str
    overrides: dict = field(default_factory=dict)
    expect: str = "finite"
    pairs: int = DEFAULT_PAIRS
    aligned: bool = True
    precision: str | None = None
    compare_fp32: bool = False
    max_iterations: int | None = None
    fit_patch_layers: bool = False


EDGE_CASES = [
    EdgeCase("baseline", "the configured preset unchanged (reference row)"),
    EdgeCase("size_min", f"smallest resolution models.check_size allows ({MIN_SIZE} px); a PatchGAN too deep "
             f"for it gets the most layers that fit", {"size": MIN_SIZE}, fit_patch_layers=True),
    EdgeCase("size_min_deep_patchgan", f"{MIN_SIZE} px with a 3-layer PatchGAN (needs 32 px): refused when the "
             f"discriminator is built", {"size": MIN_SIZE, "discriminator": "patch", "patch_layers": 3, "kernel": 4},
             expect="stopped"),
    EdgeCase("size_below_min", f"{MIN_SIZE // 2} px, one power of two below the minimum: refused",
             {"size": MIN_SIZE // 2}, expect="stopped"),
    EdgeCase("size_max", f"largest resolution the params schema accepts ({LARGEST_SIZE} px) at width 2, batch 1",
             {"size": LARGEST_SIZE, "ngf": 2, "ndf": 2, "batch_size": 1}, pairs=2, max_iterations=2),
    EdgeCase("width_min", "narrowest networks: ngf = ndf = 1", {"ngf": 1, "ndf": 1}),
    EdgeCase("width_max", f"wide networks: ngf = ndf = 128 at {MIN_SIZE} px", {"ngf": 128, "ndf": 128, "size": MIN_SIZE},
             fit_patch_layers=True, max_iterations=3),
    EdgeCase("batch1_batchnorm", "batch 1: every BatchNorm normalises a single image", {"batch_size": 1}),
    EdgeCase("batch1_batchnorm_1x1", f"batch 1, global discriminator at {MIN_SIZE} px: its last BatchNorm sees a "
             f"1 x 1 map (one value per channel): refused", {"batch_size": 1, "size": MIN_SIZE, "discriminator": "global"},
             expect="stopped"),
    EdgeCase("lr_min", "learning rate 1e-6", {"lr": 1e-6}),
    EdgeCase("lr_max", "learning rate 1e-1", {"lr": 1e-1}),
    EdgeCase("lr_absurd", "learning rate 1e3: weights explode (finite, but 1e4 x their start after two steps); "
             "must stop with TrainingDiverged naming the weight norm, saving nothing diverged", {"lr": 1e3},
             expect="stopped"),
    EdgeCase("bf16_vs_fp32", "bf16 autocast against fp32 from the same seed: outputs compared", precision="bf16",
             compare_fp32=True),
    EdgeCase("single_sample_class", "a class with a single pair (every batch repeats it; validated on it)", pairs=1),
]


def structured_pairs(size: int, n: int = DEFAULT_PAIRS, aligned: bool = True, seed: int = 0) -> PairData:
    """``n`` pairs of one class ``"c"``: inputs are random colour blocks of side ``max(1, size // 8)``;
    targets are the fixed map ``y = 255 - x[[2, 0, 1]]`` (channel rotation and inversion)."""
    generator = torch.Generator().manual_seed(seed)
    block = max(1, size // 8)
    cells = -(-size // block)
    base = torch.randint(0, 256, (n, 3, cells, cells), dtype=torch.uint8, generator=generator)
    inputs = base.repeat_interleave(block, 2).repeat_interleave(block, 3)[:, :, :size, :size].contiguous()
    targets = 255 - inputs[:, [2, 0, 1]]
    return PairData(inputs, targets, ["c"] * n, torch.full((n,), aligned, dtype=torch.bool), inputs.clone(),
                    {"c": torch.arange(n)})


def case_settings(case: EdgeCase, params: dict, iterations: int) -> dict:
    """The preset of ``params`` with ``case.overrides`` and the iteration count (capped by ``max_iterations``)."""
    settings = dict(model_settings(params), **case.overrides)
    settings["iterations"] = min(iterations, case.max_iterations) if case.max_iterations else iterations
    if case.fit_patch_layers and settings["discriminator"] == "patch":
        while settings["patch_layers"] > 1 and PatchDiscriminator(
                1, settings["patch_layers"], settings["kernel"]).output_side(settings["size"]) < 1:
            settings["patch_layers"] -= 1
    return settings


def describe(settings: dict, precision: str, pairs: int) -> str:
    """One-line summary of the settings a case ran with."""
    disc = settings["discriminator"] + (f"({settings['patch_layers']})" if settings["discriminator"] == "patch" else "")
    return (f"size={settings['size']} ngf/ndf={settings['ngf']}/{settings['ndf']} k={settings['kernel']} D={disc} "
            f"batch={settings['batch_size']} lr={settings['lr']:g} {settings['optimizer']} {precision} "
            f"it={settings['iterations']} pairs={pairs}")


def _raised_by_vtgen(exc: BaseException) -> bool:
    """True when the innermost frame of ``exc``'s traceback is vtgen code (a message written for users)."""
    frames = traceback.extract_tb(exc.__traceback__)
    return bool(frames) and Path(frames[-1].filename).resolve().is_relative_to(PACKAGE_DIR)


def _max_abs(tensors) -> float:
    values = [float(t.detach().float().abs().max()) for t in tensors if t.is_floating_point() and t.numel()]
    return max(values) if values else float("nan")


def _checkpoint_state(path: Path) -> str:
    """``none``, ``finite`` or ``non-finite``: the floating tensors of the checkpoint's two networks."""
    if not path.is_file():
        return "none"
    state = torch.load(path, map_location="cpu", weights_only=False)
    tensors = [t for key in ("generator", "discriminator") for t in state[key].values() if t.is_floating_point()]
    return "finite" if all(bool(torch.isfinite(t).all()) for t in tensors) else "non-finite"


def eval_outputs(generator: torch.nn.Module, data: PairData, count: int = 4) -> torch.Tensor:
    """Eval-mode fp32 outputs (as `vtgen generate` runs) on the first ``count`` inputs of ``data``."""
    generator.eval()
    with torch.no_grad():
        return generator(to_model_range(data.inputs[:count])).float()


@dataclass
class CaseResult:
    """A table row, the trained generator (None when stopped), the fp32 reference of a bf16 comparison,
    and the data it trained on."""

    row: dict
    generator: torch.nn.Module | None
    reference: torch.nn.Module | None
    data: PairData


def _train_once(data: PairData, settings: dict, run: dict, validation: PairData | None) -> dict:
    """One run in a temporary checkpoint folder; returns outcome, message, last logged row, generator."""
    logged: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="vtgen-stability-") as tmp:
        try:
            result = train_translator(data, settings, run, "v2t", "all", checkpoint_dir=Path(tmp),
                                      on_log=logged.append, progress=False, validation=validation)
            error = None
        except Exception as exc:  # noqa: BLE001 - classified below, never swallowed silently
            result, error = None, exc
        checkpoint = _checkpoint_state(Path(tmp) / CHECKPOINT_NAME)
    out = {"checkpoint": checkpoint, "last": logged[-1] if logged else {}, "generator": None}
    if error is not None:
        clear = isinstance(error, (TrainingDiverged, ValueError)) and _raised_by_vtgen(error)
        out["outcome"] = "broken" if checkpoint == "non-finite" else ("stopped" if clear else "crashed")
        out["message"] = f"{type(error).__name__}: {error}"
        return out
    generator = result.generator
    state = [t for t in generator.state_dict().values() if t.is_floating_point()]
    finite = (all(bool(torch.isfinite(t).all()) for t in state) and checkpoint != "non-finite"
              and bool(torch.isfinite(eval_outputs(generator, data)).all()))
    out.update(outcome="finite" if finite else "broken", message="" if finite else "non-finite model returned or saved",
               generator=generator, steps=result.steps)
    return out


def run_case(case: EdgeCase, params: dict, iterations: int = 20) -> CaseResult:
    """Train ``case`` on the preset of ``params`` (device, threads, seed from ``translation``) and return its row.

    Checkpoints every ``max(1, iterations // 2)`` steps, losses averaged over windows of ``max(1, iterations // 4)``.
    For ``compare_fp32`` cases an fp32 run from the same seed is the reference:
    ``bf16_max_abs_diff = max |G_bf16(x) - G_fp32(x)|`` over eval-mode outputs in [-1, 1] (mean likewise), and
    ``bf16_rel_diff = mean |G_bf16(x) - G_fp32(x)| / mean |G_fp32(x)|``.
    """
    settings = case_settings(case, params, iterations)
    its = settings["iterations"]
    precision = case.precision or params["translation"]["precision"]
    run = dict(params["translation"], precision=precision, checkpoint_every=max(1, its // 2),
               log_every=max(1, its // 4), resume=False)
    data = structured_pairs(settings["size"], case.pairs, case.aligned, params["translation"]["seed"])
    validation = data if case.aligned else None
    started = time.perf_counter()
    main = _train_once(data, settings, run, validation)
    reference = None
    row = {"case": case.name, "probe": case.probe, "settings": describe(settings, precision, case.pairs),
           "expected": case.expect, "outcome": main["outcome"], "message": main["message"],
           "steps": main.get("steps", float("nan")),
           **{name: main["last"].get(name, float("nan")) for name in (*LOSS_NAMES, "val_l1")},
           "max_abs_weight": float("nan"), "max_abs_running_stat": float("nan"), "checkpoint": main["checkpoint"],
           "bf16_max_abs_diff": float("nan"), "bf16_mean_abs_diff": float("nan"), "bf16_rel_diff": float("nan")}
    generator = main["generator"]
    if generator is not None:
        row["max_abs_weight"] = _max_abs(generator.parameters())
        row["max_abs_running_stat"] = _max_abs(t for k, t in generator.state_dict().items() if "running" in k)
    if case.compare_fp32:
        other = _train_once(data, settings, dict(run, precision="fp32"), validation)
        reference = other["generator"]
        if generator is not None and reference is not None:
            fp32_out = eval_outputs(reference, data)
            diff = (eval_outputs(generator, data) - fp32_out).abs()
            row["bf16_max_abs_diff"], row["bf16_mean_abs_diff"] = float(diff.max()), float(diff.mean())
            row["bf16_rel_diff"] = float(diff.mean() / fp32_out.abs().mean().clamp_min(1e-12))
        if other["outcome"] != "finite":
            row["message"] = (row["message"] + "; " if row["message"] else "") + f"fp32 reference: {other['message']}"
            if OUTCOMES.index(other["outcome"]) > OUTCOMES.index(row["outcome"]):
                row["outcome"] = other["outcome"]
    row["seconds"] = round(time.perf_counter() - started, 2)
    return CaseResult(row, generator, reference, data)


def run_stability(params: dict, iterations: int = 20) -> pd.DataFrame:
    """Run every case of :data:`EDGE_CASES` for ``iterations`` steps (fewer where a case caps them);
    one row per case with the columns of :data:`COLUMNS`."""
    rows = [run_case(case, params, iterations).row for case in EDGE_CASES]
    return pd.DataFrame(rows, columns=COLUMNS)


def write_stability(table: pd.DataFrame, out_dir: str | Path) -> dict:
    """Write ``stability.csv`` and ``summary.json`` (counts per outcome, cases not reaching their expected
    outcome) into ``out_dir`` and return the summary. Raises RuntimeError, writing nothing, when any case is
    ``broken`` or ``crashed``: the contract is that none is."""
    counts = {outcome: int((table["outcome"] == outcome).sum()) for outcome in OUTCOMES}
    failed = table[table["outcome"].isin(["broken", "crashed"])]
    if len(failed):
        raise RuntimeError("stability: " + "; ".join(f"{r.case} {r.outcome} ({r.message})"
                                                     for r in failed.itertuples()))
    summary = {"cases": len(table), **counts,
               "unexpected": [r.case for r in table.itertuples() if r.outcome != r.expected]}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    table.to_csv(out_dir / "stability.csv", index=False)
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
