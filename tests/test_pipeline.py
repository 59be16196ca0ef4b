"""The stage table: both workflows come from it, code dependencies follow imports, layers import one way."""

from __future__ import annotations

import pytest
import copy
import json
import re
import subprocess
import sys
from pathlib import Path

import yaml

from conftest import ENV, REPO, make_project, tiny_params
from vtgen import pipeline
from vtgen.pipeline import STAGES, Stage, code_deps, dvc_yaml, snakemake_rule, stages, write_dvc_files


def by_name(name: str) -> Stage:
    return next(s for s in STAGES if s.name == name)


def test_committed_dvc_files_are_what_the_stage_table_writes(default_params):
    assert write_dvc_files(default_params, REPO, check=True) == [], "run `vtgen workflow` and commit the result"


def test_import_layers_and_stage_independence_hold():
    result = subprocess.run([str(Path(sys.executable).parent / "lint-imports")], cwd=REPO, capture_output=True, text=True,
                            env=ENV)
    assert result.returncode == 0, result.stdout[-3000:]
    assert result.stdout.count("KEPT") == 2


def test_code_dependencies_are_the_modules_each_stage_imports():
    generate = code_deps(by_name("generate"))
    assert {"src/vtgen/stages/generate.py", "src/vtgen/core/models.py", "src/vtgen/core/gan.py",
            "src/vtgen/io/checkpoints.py", "src/vtgen/io/images.py"} <= set(generate)
    assert "src/vtgen/stages/train.py" not in generate  # stages never import each other
    score = code_deps(by_name("score"))
    assert {"src/vtgen/core/metrics.py", "src/vtgen/core/distribution.py"} <= set(score)
    assert "src/vtgen/core/translator.py" not in score and "src/vtgen/stages/classify.py" not in score
    train = code_deps(by_name("train"))
    assert "src/vtgen/core/models.py" in train and "src/vtgen/stages/score.py" not in train
    assert "src/vtgen/io/templates" in code_deps(by_name("report"))
    # every listed file exists, so a tool can hash it
    for stage in STAGES:
        for path in code_deps(stage):
            assert (REPO / path).exists(), (stage.name, path)


def test_a_project_whose_vtgen_runs_from_elsewhere_gets_a_clear_error(tmp_path):
    """``vtgen workflow`` in a project while the vtgen that runs is installed outside it: a message naming both
    places and the remedy, not pathlib's bare 'is not in the subpath of'."""
    with pytest.raises(ValueError, match=r"outside this project .*PYTHONPATH=src") as error:
        write_dvc_files(yaml.safe_load((REPO / "params.yaml").read_text()), tmp_path)
    assert str(tmp_path.resolve()) in str(error.value) and str(REPO / "src" / "vtgen") in str(error.value)


def test_render_exists_only_for_the_synthetic_dataset(default_params):
    generic = copy.deepcopy(default_params)
    generic["dataset"] = {"source": "generic", "path": "my_data"}
    assert "render" in [s.name for s in stages(default_params)]
    assert "render" not in [s.name for s in stages(generic)]
    written = yaml.safe_load(dvc_yaml(generic, "main"))["stages"]
    assert "render" not in written and written["ingest"]["deps"][0] == "${dataset.path}"
    assert "data/raw/synthetic" not in pipeline.outputs(generic)


def test_snakemake_rule_expands_other_stages_wildcards_and_keeps_its_own(default_params):
    params = copy.deepcopy(default_params)
    params["translation"]["scope"] = ["all", "denim"]
    rule = snakemake_rule(by_name("generate"), params)
    assert rule["outputs"] == ["data/generated/{direction}"]
    assert {"models/{direction}/all", "models/{direction}/denim"} <= set(rule["inputs"])
    assert rule["command"](dict(direction="t2v")) == (
        "vtgen generate --params params.yaml --direction t2v --pairs data/pairs --models models/t2v "
        "--out data/generated/t2v")
    assert rule["params"]["translation_scope"] == ["all", "denim"]
    train = snakemake_rule(by_name("train"), params)
    assert train["inputs"][0] == "data/settings/{direction}"  # its params values, one file per direction
    assert train["threads"] == params["translation"]["threads"]
    settings = snakemake_rule(by_name("settings"), params)
    assert settings["params"] == {} and settings["inputs"][-1] == ".vtgen/params/settings/{direction}.json"
    assert settings["local"] and not train["local"]  # a job of a second: never a cluster job


def test_a_modality_s_classifier_waits_for_its_own_generator_only(default_params, tmp_path):
    classify = by_name("classify")
    rule = snakemake_rule(classify, default_params)
    # Snakemake: the input function gives each modality the direction that makes its images
    visual, tactile = (rule["input"](dict(modality=m)) for m in ("visual", "tactile"))
    assert "data/generated/t2v" in visual and "data/generated/v2t" not in visual
    assert "data/generated/v2t" in tactile and "data/generated/t2v" not in tactile
    # DVC: one foreach job per modality, its generated images named through the mapping
    written = yaml.safe_load(dvc_yaml(default_params, "main"))["stages"]["classify"]
    assert written["foreach"] == {"visual": {"producer": "t2v"}, "tactile": {"producer": "v2t"}}
    assert "data/generated/${item.producer}" in written["do"]["deps"]
    assert written["do"]["outs"] == [{"data/classify/${key}": {"persist": True}}]
    # the content records' jobs read the same
    jobs = {job.name: job for job in pipeline.jobs(default_params)}
    assert [p for p in jobs["classify@visual"].inputs if p.startswith("data/generated")] == ["data/generated/t2v"]
    assert [p for p in jobs["classify@tactile"].inputs if p.startswith("data/generated")] == ["data/generated/v2t"]
    # a stage that derives a placeholder from a wildcard it does not have is refused
    odd = Stage("odd", "vtgen.stages.pairs", "true", inputs=("data/generated/{producer}",), outputs=("data/odd/{direction}",))
    with pytest.raises(ValueError, match="producer"):
        pipeline.dvc_stage(odd, REPO)


@pytest.mark.slow
def test_snakemake_plans_a_modality_s_classifier_without_the_other_direction(tmp_path):
    project = make_project(tmp_path / "project", tiny_params())
    dry = subprocess.run(["snakemake", "-n", "data/classify/visual"], cwd=project, env=ENV, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stdout[-3000:] + dry.stderr[-3000:]
    planned = re.findall(r"(?:local)?rule (\w+):\n(?:.*\n)*?    output: (\S+)", dry.stdout)
    outputs = {out for _, out in planned}
    assert {"models/t2v/all", "data/generated/t2v", "data/classify/visual"} <= outputs
    assert not {"models/v2t/all", "data/generated/v2t", "data/classify/tactile"} & outputs, sorted(outputs)


def test_a_dropped_input_is_no_change_but_a_new_or_changed_one_is(default_params, tmp_path, monkeypatch):
    from vtgen.io.contents import Hasher, write_record

    monkeypatch.chdir(tmp_path)
    job = next(j for j in pipeline.jobs(default_params) if j.name == "classify@visual")
    for path in job.inputs:
        if not (tmp_path / path).exists():
            (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
            (tmp_path / path).write_text(path)
    (tmp_path / job.outputs[0]).mkdir(parents=True)
    (tmp_path / job.outputs[0] / "summary.json").write_text("{}")
    inputs = pipeline.input_hashes(job, default_params, Hasher())
    # recorded when the stage still read both directions' images: the dropped one does not rerun it
    write_record(job.record_dir, job.name, {**inputs, "data/generated/v2t": "0" * 32}, list(job.outputs), Hasher())
    assert pipeline.job_problem(job, default_params, Hasher()) is None
    # an input it reads that changed, or one the record lacks, does
    (tmp_path / "data/generated/t2v").write_text("other images")
    assert pipeline.job_problem(job, default_params, Hasher()) == "input data/generated/t2v changed since it ran"
    write_record(job.record_dir, job.name, {k: v for k, v in inputs.items() if k != "data/roi"}, list(job.outputs),
                 Hasher())
    (tmp_path / "data/generated/t2v").write_text("data/generated/t2v")
    assert pipeline.job_problem(job, default_params, Hasher()) == "input data/roi changed since it ran"


def test_times_are_not_content_and_split_off_a_record_and_back(tmp_path, monkeypatch):
    from vtgen.io.contents import Hasher, write_record
    from vtgen.io.timing import merge_times, read_with_times, split_times

    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "summary.json").write_text('{"tiles": 4}')
    (folder / "timing.json").write_text('{"seconds": 1.5}')
    first = Hasher().hash("out")
    write_record("out", "job", {}, ["out"], Hasher())
    (folder / "timing.json").write_text('{"seconds": 2.5, "finished": "later"}')  # the same data, run again
    assert Hasher().hash("out") == first and damage_of("out") is None
    (folder / "summary.json").write_text('{"tiles": 5}')  # the data changed
    assert Hasher().hash("out") != first and damage_of("out") == "out/summary.json differs from what was written (md5)"
    assert "timing.json" in Path(REPO / ".dvcignore").read_text().split()  # DVC ignores it too

    record = {"steps": 8, "wall_seconds": 3.0, "capacity": {"mode": "auto", "compute": {"gflop": 2, "seconds": 1.0},
                                                            "probe": {"16": {"val": 0.5, "seconds": 0.4}}}}
    data, times = split_times(record, {"wall_seconds", "seconds"})
    assert data == {"steps": 8, "capacity": {"mode": "auto", "compute": {"gflop": 2}, "probe": {"16": {"val": 0.5}}}}
    assert times == {"wall_seconds": 3.0, "capacity": {"compute": {"seconds": 1.0}, "probe": {"16": {"seconds": 0.4}}}}
    assert merge_times(data, times) == record
    (folder / "train.json").write_text(json.dumps(data))
    (folder / "timing.json").write_text(json.dumps({**times, "stage": "train", "seconds": 9.0, "peak_rss_mb": 1}))
    assert read_with_times(folder / "train.json") == record  # the command's own wall time and memory left out


def damage_of(folder: str) -> str | None:
    from vtgen.io.contents import damage, Hasher, read_record

    return damage(read_record(folder), [folder], Hasher())


def test_a_direction_s_settings_change_only_with_its_own_values(default_params, tmp_path):
    params = copy.deepcopy(default_params)
    params["translation"]["class_gan"]["upsample"] = {"v2t": "transpose", "t2v": "resize"}
    pipeline.write_params_records(params, tmp_path)
    records = {d: (tmp_path / f".vtgen/params/settings/{d}.json").read_text() for d in ("v2t", "t2v")}
    # under translation.recipe auto a record holds the settings of each block auto may choose (fabric sets upsample)
    assert {d: sorted(json.loads(text)) for d, text in records.items()} == {"v2t": ["fabric", "none"], "t2v": ["fabric", "none"]}
    settings = {d: json.loads(text)["none"] for d, text in records.items()}
    assert settings["t2v"]["translation"]["class_gan"]["upsample"] == "resize"
    assert settings["v2t"]["translation"]["class_gan"]["upsample"] == "transpose"
    assert settings["v2t"]["translation"]["conditioning"] == params["translation"]["conditioning"]["v2t"]
    assert settings["v2t"]["preset"] == params["presets"]["fast"]

    params["translation"]["class_gan"]["upsample"]["t2v"] = "transpose"  # T2V's value alone changes
    pipeline.write_params_records(params, tmp_path)
    assert (tmp_path / ".vtgen/params/settings/v2t.json").read_text() == records["v2t"]
    assert (tmp_path / ".vtgen/params/settings/t2v.json").read_text() != records["t2v"]
    params["translation"]["class_gan"]["r1"] = 5  # a value both directions read
    pipeline.write_params_records(params, tmp_path)
    assert (tmp_path / ".vtgen/params/settings/v2t.json").read_text() != records["v2t"]


@pytest.mark.slow
def test_a_new_stage_in_the_table_appears_in_both_workflows_with_its_code(tmp_path):
    project = make_project(tmp_path / "project", tiny_params())
    table = project / "src/vtgen/pipeline.py"
    table.write_text(table.read_text().replace(
        "    # studies: outside the main job",
        '    Stage("count", "vtgen.stages.pairs", "vtgen pairs --params params.yaml --tiles data/roi/tiles.parquet "\n'
        '          "--out data/count", inputs=("data/roi",), outputs=("data/count",), params=("pairing",)),\n'
        "    # studies: outside the main job"))
    env = {**ENV, "PYTHONPATH": str(project / "src")}
    subprocess.run([sys.executable, "-m", "vtgen", "workflow"], cwd=project, env=env, check=True, capture_output=True)
    written = yaml.safe_load((project / "dvc.yaml").read_text())["stages"]["count"]
    # persist: a `dvc repro` that the run lock then refuses must not have removed the output (issue 25)
    assert written["cmd"].endswith("--out data/count") and written["outs"] == [{"data/count": {"persist": True}}]
    assert "src/vtgen/stages/pairs.py" in written["deps"] and "src/vtgen/io/tables.py" in written["deps"]
    dry = subprocess.run(["snakemake", "-n", "-p", "data/count"], cwd=project, env=env, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stdout[-3000:] + dry.stderr[-3000:]
    block = re.search(r"rule count:\n(.*?)\n\n", dry.stdout, flags=re.S)
    assert block and "src/vtgen/stages/pairs.py" in block[1] and "data/roi" in block[1]


def test_a_stage_outside_snakemake_gets_the_threads_snakemake_would_give_it(monkeypatch, default_params):
    """Under DVC (no OMP_NUM_THREADS) a job runs with its declared threads in torch, BLAS and the environment, as
    under Snakemake, and everything is restored afterwards; under Snakemake its environment decides."""
    import os

    import torch
    from threadpoolctl import threadpool_info

    from vtgen.cli import THREAD_VARIABLES, threads_as_snakemake
    from vtgen.pipeline import jobs

    main_jobs = {job.name: job for job in jobs(default_params, "main")}
    two_thread_train = {**default_params, "translation": {**default_params["translation"], "threads": 2}}
    for name in THREAD_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        with threads_as_snakemake(main_jobs["score"], default_params):  # no threads parameter: 1, as Snakemake
            assert torch.get_num_threads() == 1
            assert all(os.environ[name] == "1" for name in THREAD_VARIABLES)
            assert {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"} <= {1}
        assert torch.get_num_threads() == 2 and not any(name in os.environ for name in THREAD_VARIABLES)
        torch.set_num_threads(1)
        with threads_as_snakemake(main_jobs["train@v2t-all"], two_thread_train):  # translation.threads
            assert torch.get_num_threads() == 2 and os.environ["OMP_NUM_THREADS"] == "2"
        assert torch.get_num_threads() == 1
        monkeypatch.setenv("OMP_NUM_THREADS", "2")  # Snakemake's environment: left as it is
        with threads_as_snakemake(main_jobs["score"], default_params):
            assert torch.get_num_threads() == 1 and os.environ["OMP_NUM_THREADS"] == "2"
        with threads_as_snakemake(None, default_params):  # not a declared job
            assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)
