"""Studies: overrides, the Pareto frontier, capacity auto, DVC experiment commands, and the study pipeline end to end."""

from __future__ import annotations

import html
import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import ENV, make_project, run, tiny_params

from vtgen.io.params import ParamsError, validate_params
from vtgen.studies.study import apply_overrides, choose_capacity, dvc_queue_command, is_default, pareto_front, variant_overrides


def test_overrides_set_existing_keys_and_resolve_the_preset_alias(default_params):
    merged = apply_overrides(default_params, {"preset.batch_size": 8, "roi.size": 128})
    preset = default_params["translation"]["preset"]
    assert merged["presets"][preset]["batch_size"] == 8
    assert merged["roi"]["size"] == 128
    assert default_params["roi"]["size"] == 64  # the input is not modified


@pytest.mark.parametrize("overrides, message", [
    ({"preset.batch_sise": 8}, "no key 'presets.fast.batch_sise'"),
    ({"rio.size": 64}, "no key 'rio'"),
    ({"roi.size.x": 1}, "no key 'roi.size.x'"),
])
def test_overrides_refuse_unknown_keys(default_params, overrides, message):
    with pytest.raises(ValueError, match=message.replace(".", r"\.")):
        apply_overrides(default_params, overrides)


def test_overrides_must_give_valid_params(default_params):
    with pytest.raises(ParamsError, match="size"):
        apply_overrides(default_params, {"preset.size": 48})


@pytest.mark.slow
def test_every_declared_study_resolves_to_valid_params(default_params):
    for kind, table in (("experiments", default_params["studies"]["experiments"]["runs"]),
                        ("tradeoff", default_params["studies"]["tradeoff"]["settings"])):
        for name in table:
            apply_overrides(default_params, variant_overrides(default_params, kind, name))
    marked = [n for n in default_params["studies"]["tradeoff"]["settings"]
              if is_default(default_params, apply_overrides(default_params, variant_overrides(default_params, "tradeoff", n)))]
    assert marked == ["main_default"]  # exactly one trade-off setting is the main job's own
    for name in default_params["studies"]["tradeoff"]["settings"]:
        if name != "main_default":  # capacity auto would probe widths and stop early: not the setting named
            variant = apply_overrides(default_params, variant_overrides(default_params, "tradeoff", name))
            assert variant["translation"]["capacity"]["mode"] == "fixed", name


def test_schema_refuses_a_malformed_study(default_params):
    default_params["studies"]["experiments"]["runs"]["bad"] = {"about": "", "paper": "", "mode": "sideways",
                                                               "directions": ["v2t"], "set": {}}
    with pytest.raises(ParamsError, match="sideways"):
        validate_params(default_params)


def test_dvc_queue_command_carries_base_and_own_overrides(default_params):
    command = dvc_queue_command(default_params, "double_resolution")
    assert command[:6] == ["dvc", "exp", "run", "--queue", "-n", "double_resolution"]
    values = dict(arg.split("=", 1) for arg in command[7::2])
    assert values == {"presets.fast.iterations": "400", "translation.threads": "1", "roi.size": "128", "presets.fast.size": "128"}
    assert dvc_queue_command(default_params, "round_trip") is None  # needs the studies runner


def test_pareto_front():
    seconds = np.array([10, 20, 30, 40, 15])
    quality = np.array([0.5, 0.6, 0.55, 0.7, 0.5])
    # 30 s/0.55 is beaten by 20 s/0.6; 15 s/0.5 by 10 s/0.5
    assert pareto_front(seconds, quality).tolist() == [True, True, False, True, False]


def test_capacity_picks_the_cheapest_setting_within_tolerance():
    per_class = pd.DataFrame({"felt": [0.60, 0.61, 0.62], "printed": [0.30, 0.40, 0.50]},
                             index=["small", "medium", "large"])
    seconds = pd.Series({"small": 10.0, "medium": 30.0, "large": 100.0})
    choice = choose_capacity(per_class, seconds, tolerance=0.02)
    assert choice["felt"]["setting"] == "small"      # 0.60 >= 0.62 - 0.02
    assert choice["printed"]["setting"] == "large"   # only the best is within 0.02
    assert choose_capacity(per_class, seconds, tolerance=0.0)["felt"]["setting"] == "large"
    assert choose_capacity(per_class, seconds, tolerance=1.0)["printed"]["setting"] == "small"


TINY_STUDIES = {
    "experiments": {
        "base": {"preset.iterations": 4},
        "runs": {
            "default": {"about": "default", "paper": "about 0.90", "mode": "standard", "directions": ["v2t"], "set": {}},
            "cloth_types": {"about": "per class", "paper": "-", "mode": "per_class", "directions": ["v2t"], "set": {}},
            "round_trip": {"about": "paired", "paper": "-", "mode": "round_trip", "directions": ["v2t", "t2v"], "set": {}},
        },
    },
    "tradeoff": {"direction": "v2t", "seeds": [0, 1],
                 "base": {"preset.iterations": 4, "generate.train_share": 0.0, "translation.capacity.mode": "fixed"},
                 "settings": {"main_default": {"preset.iterations": 10, "translation.capacity.mode": "auto"},
                              "narrow": {"preset.ngf": 4, "preset.ndf": 4},
                              "size_16": {"roi.size": 16, "preset.size": 16, "preset.patch_layers": 1}}},
    "capacity": {"tolerance": 0.05},
}


@pytest.mark.e2e
def test_studies_pipeline_end_to_end(tmp_path):
    """`snakemake studies` on a tiny project: every study output, the frontier files and the report."""
    params = tiny_params()
    params["classify"].update(epochs=1)
    params["studies"] = TINY_STUDIES
    project = make_project(tmp_path / "project", params)
    run(["git", "init", "-q"], project)  # dvclive reads the Git revision
    run(["git", "-c", "user.email=t@t", "-c", "user.name=t", "commit", "-q", "--allow-empty", "-m", "init"], project)
    run(["snakemake", "--cores", "2", "studies"], project)

    frontier = pd.read_csv(project / "data/studies/frontier/frontier.csv")
    assert set(frontier["setting"]) == {"main_default", "narrow", "size_16"}
    assert frontier["is_default"].tolist().count(True) == 1
    assert frontier.loc[frontier["is_default"], "setting"].item() == "main_default"
    assert frontier["on_frontier"].any() and (frontier["seeds"] == 2).all()
    assert frontier.loc[frontier["setting"] == "size_16", "changes_data"].item()
    assert np.isfinite(frontier[["seconds", "quality"]].to_numpy()).all()
    narrow = json.loads((project / "data/studies/tradeoff/narrow/result.json").read_text())
    assert {r["v2t"]["trained"]["all"]["width"] for r in narrow["runs"].values()} == {4}  # the width the setting names
    default = json.loads((project / "data/studies/tradeoff/main_default/result.json").read_text())
    assert {r["v2t"]["trained"]["all"]["capacity"] for r in default["runs"].values()} == {"auto"}
    capacity = json.loads((project / "data/studies/frontier/capacity.json").read_text())
    assert set(capacity["classes"]) == set(params["synthetic"]["classes"])
    assert all(c["setting"] in ("main_default", "narrow") for c in capacity["classes"].values())  # size_16 changes tiles
    for name in ("all_settings", "pareto_frontier", "main_default"):
        assert {"seconds", "quality"} <= set(pd.read_csv(project / f"data/studies/frontier/{name}.csv").columns)

    per_class = json.loads((project / "data/studies/experiments/cloth_types/result.json").read_text())
    assert {c: v["setting"] for c, v in per_class["runs"]["run"]["classes"].items()} == \
        {c: v["setting"] for c, v in capacity["classes"].items()}
    round_trip = pd.read_csv(project / "data/studies/experiments/round_trip/quality.csv")
    assert set(round_trip["direction"]) == {"round trip, T2V on real pairs only", "round trip, T2V on 50/50 real and generated"}
    assert round_trip["quality"].between(-1, 1).all()

    page = html.unescape((project / "reports/studies/index.html").read_text())
    for text in ("SYNTHETIC DATA", "The paper's experiments", "cloth_types", "round_trip", "Speed against accuracy",
                 "figures/pareto.png", "Capacity auto", "Numerical stability"):
        assert text in page
    assert (project / "reports/studies/figures/pareto.png").stat().st_size > 10_000

    # DVC runs the same study commands (its own dvc.yaml, from the project root; written on request, not committed)
    subprocess.run([sys.executable, "-m", "vtgen", "workflow", "--studies"], cwd=project, check=True,
                   env={**ENV, "PYTHONPATH": str(project / "src")}, capture_output=True)
    stages = yaml.safe_load((project / "workflow/studies/dvc.yaml").read_text())["stages"]
    smk = run(["snakemake", "-n", "-p", "--forceall", "studies"], project).stdout
    for stage in stages.values():
        command = (stage.get("do") or stage)["cmd"]
        if "${key}" in command:
            command = command.replace("${key}", "narrow" if "tradeoff" in command else "default")
        assert command in smk, command
