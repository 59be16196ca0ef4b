"""Capacity auto in the train stage: width probe and per-class early stopping."""

from __future__ import annotations

import numpy as np
import torch

from conftest import TINY_MODEL
from vtgen.stages.train import all_settled, PairData, settled_classes, train_capacity_auto, validation_by_class

SETTINGS = dict(TINY_MODEL, gan_loss="bce", l1_weight=100.0, optimizer="adam", lr=0.002, betas=[0.5, 0.999],
                noise=False, batch_size=4, iterations=240)
CAPACITY = dict(mode="auto", widths=[2, 16], probe_iterations=80, eval_every=40, tolerance=0.02, patience=2)
RUN = dict(device="cpu", precision="fp32", threads=2, checkpoint_every=10**6, resume=False, log_every=20, seed=0,
           capacity=CAPACITY)


def easy_and_hard(n: int, seed: int, size: int = 32) -> PairData:
    """Class 'easy': any input -> one flat grey; class 'hard': a random fine texture -> its inverse with the
    channels rotated (every pixel must be carried through)."""
    rng = np.random.default_rng(seed)
    inputs, targets, classes = [], [], []
    for name in ("easy", "hard"):
        for _ in range(n):
            texture = rng.integers(0, 256, (3, size // 2, size // 2)).repeat(2, 1).repeat(2, 2).astype(np.uint8)
            inputs.append(texture)
            targets.append(np.full_like(texture, 128) if name == "easy" else 255 - texture[[2, 0, 1]])
            classes.append(name)
    x = torch.from_numpy(np.stack(inputs))
    return PairData(x, torch.from_numpy(np.stack(targets)), classes, torch.ones(len(classes), dtype=torch.bool),
                    x.clone(), {c: torch.tensor([i for i, k in enumerate(classes) if k == c]) for c in ("easy", "hard")})


def test_settled_classes_waits_for_patience_and_names_the_step_needed():
    rows = [{"step": s, "val_by_class": {"a": a, "b": b}} for s, a, b in
            [(10, 0.50, 0.1), (20, 0.80, 0.2), (30, 0.81, 0.4), (40, 0.80, 0.6)]]
    settled = settled_classes(rows, tolerance=0.02, patience=2)
    assert settled == {"a": 20, "b": None}  # a: best rose 0.01 over 2 validations, first within 0.02 at step 20
    assert settled_classes(rows[:2], 0.02, 2) == {"a": None, "b": None}  # too few validations yet


def test_a_flat_class_below_its_floor_has_not_settled():
    """A class still at chance is on the plateau before it learns, not settled (capacity auto's judge)."""
    rows = [{"step": s, "val_by_class": {"a": 0.03, "b": 0.6}} for s in (10, 20, 30, 40)]
    assert settled_classes(rows, 0.02, 2) == {"a": 10, "b": 10} and all_settled(rows, 0.02, 2)
    floored = settled_classes(rows, 0.02, 2, floor={"a": 0.083, "b": 0.083})
    assert floored == {"a": None, "b": 10} and not all_settled(rows, 0.02, 2, {"a": 0.083})
    assert settled_classes(rows, 0.02, 2, floor={"a": 0.03}) == {"a": 10, "b": 10}  # reaching the floor is enough


def test_one_lucky_validation_does_not_clear_the_floor():
    """The floor is read on the mean of the last ``patience`` scores, not the best: a class scored 0.2 once on a
    few images and 0 since has a flat best above its floor, but has not learnt (the fabric recipe's rib knit)."""
    rows = [{"step": s, "val_by_class": {"a": a}} for s, a in [(10, 0.2), (20, 0.0), (30, 0.0), (40, 0.0)]]
    assert settled_classes(rows, 0.02, 2) == {"a": 10}  # no floor: a plateau
    assert settled_classes(rows, 0.02, 2, floor={"a": 0.083}) == {"a": None}
    recovered = rows + [{"step": 50, "val_by_class": {"a": 0.1}}, {"step": 60, "val_by_class": {"a": 0.1}}]
    assert settled_classes(recovered, 0.02, 2, floor={"a": 0.083}) == {"a": 10}  # held above it for 2 validations


def test_easy_class_gets_the_smaller_or_shorter_setting_and_train_json_says_so():
    result, settings, record = train_capacity_auto(easy_and_hard(8, 0), easy_and_hard(3, 1), SETTINGS, RUN, "v2t",
                                                   "all", progress=False)
    easy, hard = record["per_class"]["easy"], record["per_class"]["hard"]
    assert easy["width_needed"] <= hard["width_needed"]
    easy_steps = easy["settled_at_step"] or record["steps"]
    hard_steps = hard["settled_at_step"] or record["steps"]
    assert easy_steps <= hard_steps
    assert easy["width_needed"] < hard["width_needed"] or easy_steps < hard_steps
    assert settings["ngf"] == record["chosen_width"] == max(easy["width_needed"], hard["width_needed"])
    assert result.steps == record["steps"] <= SETTINGS["iterations"]
    compute = record["compute"]
    assert compute["gflop"] < compute["fixed_large_gflop"] and 0 < compute["saved_share"] < 1
    assert set(record["probe"]) == {"2", "16"}


def test_a_rerun_takes_probes_and_the_finished_run_from_their_checkpoints_and_logs_what_the_first_run_logged(tmp_path):
    """A rerun whose checkpoints match takes the probes from them and the chosen width's finished run from its
    checkpoint, training nothing. Its log (and so its early-stopping decision) and its generator equal the first
    run's, where the final run continued the probe: the probe validates at the same steps."""
    def logged(history):
        return [{k: v for k, v in row.items() if k not in ("images_per_s", "seconds")} for row in history]

    settings = dict(SETTINGS, iterations=80)
    run = dict(RUN, resume=True, checkpoint_every=40,  # patience 10: runs to the end
               capacity=dict(CAPACITY, probe_iterations=40, eval_every=20, patience=10))
    first, _, record = train_capacity_auto(easy_and_hard(8, 0), easy_and_hard(3, 1), settings, run, "v2t", "all",
                                           tmp_path, progress=False)
    again, _, again_record = train_capacity_auto(easy_and_hard(8, 0), easy_and_hard(3, 1), settings, run, "v2t", "all",
                                                 tmp_path, progress=False)
    assert record["steps"] == 80 and again.resumed_from == 80 and again_record["steps"] == 80
    assert [r["step"] for r in first.history if "val_by_class" in r] == [20, 40, 60, 80]
    assert logged(again.history) == logged(first.history)
    assert all(torch.equal(a, b) for a, b in zip(first.generator.state_dict().values(),
                                                  again.generator.state_dict().values()))


def test_the_report_table_gives_each_class_its_floor_and_says_when_one_never_settled():
    from vtgen.io.report_tables import capacity_table

    compute = {"gflop": 10.0, "fixed_large_gflop": 40.0, "saved_share": 0.75, "seconds": 5.0,
               "fixed_large_seconds_estimate": 20.0}
    run = {"direction": "v2t", "scope": "all", "capacity": {
        "mode": "auto", "chosen_width": 32, "steps": 1500, "compute": compute,
        "per_class": {"felt": {"width_needed": 16, "settled_at_step": 400},
                      "satin": {"width_needed": 32, "settled_at_step": None, "floor": 0.0833}}}}
    table = capacity_table([run]).set_index("class")
    assert table.loc["satin", "settled at step"] == "not settled by 1500" and table.loc["satin", "floor"] == 0.0833
    assert table.loc["felt", "settled at step"] == 400 and table.loc["felt", "floor"] == ""  # aligned: no floor


def test_per_class_validation_builds_no_autograd_graph():
    """validation_by_class scores in no-grad mode: every early-stopping check would otherwise keep the
    generator's activation graph alive for the whole validation split."""
    class Recorder(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.scale = torch.nn.Parameter(torch.ones(1))
            self.grad_modes = []

        def forward(self, x, z=None):
            self.grad_modes.append(torch.is_grad_enabled())
            return x * self.scale

    generator = Recorder()
    scores = validation_by_class(generator, easy_and_hard(2, 1))
    assert set(scores) == {"easy", "hard"} and generator.grad_modes and not any(generator.grad_modes)
