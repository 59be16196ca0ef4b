"""End-to-end: Snakemake and DVC run the data stages on a tiny configuration and agree."""

import json
import math
import re
import subprocess
from pathlib import Path

import pandas as pd
import pytest
import yaml

from conftest import ENV, make_project, run, tiny_params

pytestmark = pytest.mark.e2e
STAGES = ["render", "ingest", "roi", "pairs", "train", "generate", "score", "classify", "report"]
BENCHMARKS = ["render", "ingest", "roi", "pairs", "train_v2t_all", "train_t2v_all", "generate_v2t", "generate_t2v",
              "score", "classify_visual", "classify_tactile"]
REPORT_OUTPUTS = "reports/figures, reports/index.html, reports/metrics.json, reports/summary.md"
OUTPUTS = {"data/raw/synthetic", "data/ingest", "data/roi", "data/pairs", "models/v2t/all", "models/t2v/all",
           "data/generated/v2t", "data/generated/t2v", "data/scores", "data/classify/visual", "data/classify/tactile",
           REPORT_OUTPUTS}


def output_tables(project: Path) -> dict[str, pd.DataFrame]:
    return {
        name: pd.read_parquet(project / name)
        for name in ("data/ingest/manifest.parquet", "data/roi/tiles.parquet",
                     "data/pairs/v2t.parquet", "data/pairs/t2v.parquet", "data/pairs/splits.parquet",
                     "data/generated/v2t/generated.parquet", "data/generated/t2v/generated.parquet")
    }


def data_files(project: Path) -> set[str]:
    return {str(p.relative_to(project)) for p in (project / "data").rglob("*") if p.is_file() and p.name not in (".gitignore", ".snakemake_timestamp")}


def test_snakemake_runs_data_stages(snakemake_project):
    project, result = snakemake_project
    tables = output_tables(project)
    manifest = tables["data/ingest/manifest.parquet"]
    assert len(manifest) == 3 * 6 * 2
    assert set(manifest["class"]) == {"plain_weave", "denim", "felt"}
    assert (manifest[["width", "height"]] == 64).all().all()
    tiles = tables["data/roi/tiles.parquet"]
    assert len(tiles) == len(manifest)  # centre crop: one tile per image
    assert all((project / "data/roi/tiles" / p).is_file() for p in tiles["tile_path"])
    for direction in ("v2t", "t2v"):
        pairs = tables[f"data/pairs/{direction}.parquet"]
        assert pairs["aligned"].all()  # the default synthetic data is aligned
        assert set(pairs["split"]) == {"train", "val", "test"}
        assert all((project / p).is_file() for p in pairs["input_path"])
    for direction in ("v2t", "t2v"):
        generated = tables[f"data/generated/{direction}/generated.parquet"]
        assert set(generated["split"]) == {"train", "test"}
        assert (generated["ground_truth_path"] != "").all()  # aligned data: every output has its ground truth
        assert all((project / p).is_file() for p in generated["output_path"])
        summary = json.loads((project / f"models/{direction}/all/train.json").read_text())
        assert summary["steps"] == 10 and all(math.isfinite(v) for v in summary["final_losses"].values())
    for name in BENCHMARKS:
        assert (project / "logs/benchmarks" / f"{name}.tsv").is_file()
    # a finished workflow has nothing left to do
    again = run(["snakemake", "--cores", "2", "-n"], project)
    assert "Nothing to be done" in again.stdout + again.stderr


def test_snakemake_and_dvc_run_the_same_commands_and_outputs(snakemake_project, tmp_path):
    smk, _ = snakemake_project
    project = make_project(tmp_path / "dvc", tiny_params())
    run(["git", "init", "-q"], project)
    run(["dvc", "init", "-q"], project)
    run(["dvc", "config", "core.analytics", "false"], project)
    run(["git", "add", "-A"], project)
    run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "project"], project)
    run(["dvc", "repro"], project)
    # the main job is dvc.yaml; workflow/studies/dvc.yaml holds the studies, which `dvc repro` leaves alone
    assert "up to date" in run(["dvc", "status", "dvc.yaml"], project).stdout.lower()
    assert not (project / "data/studies").exists()

    # the same command, inputs and outputs per job (DVC's matrix and foreach stages resolved by DVC itself)
    dry = run(["snakemake", "--cores", "2", "-n", "-p", "--forceall"], smk).stdout
    jobs = {", ".join(sorted(m["output"].split(", "))): m for m in re.finditer(
        r"rule (?P<rule>\w+):\n    input: (?P<input>[^\n]*)\n    output: (?P<output>[^\n]*)\n.*?Shell command: (?P<cmd>[^\n]*)",
        dry, flags=re.S)}
    from dvc.repo import Repo

    stages = [s for s in Repo(str(project)).index.stages if s.path_in_repo == "dvc.yaml"]
    def outputs(stage) -> str:
        return ", ".join(sorted(str(o.def_path) for o in stage.outs))

    assert set(jobs) == {outputs(stage) for stage in stages} == OUTPUTS
    assert {stage.name.split("@")[0] for stage in stages} == {job["rule"] for job in jobs.values()} == set(STAGES)
    for stage in stages:
        job = jobs[outputs(stage)]
        deps = {str(d.def_path) for d in stage.deps} - {"params.yaml"}
        # a DVC dependency on a folder covers the Snakemake inputs inside it (generate reads models/<direction>/)
        inputs = {next((d for d in deps if i.startswith(d + "/")), i) for i in job["input"].split(", ")}
        assert stage.cmd == job["cmd"], stage.name
        assert deps == inputs, stage.name

    # training depends on the selected preset only: editing another preset changes nothing
    edited = tiny_params()
    edited["presets"]["paper"]["ngf"] = 8
    (project / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
    assert "up to date" in run(["dvc", "status", "dvc.yaml"], project).stdout.lower()
    edited["presets"]["fast"]["iterations"] = 12
    (project / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
    changed = run(["dvc", "status", "--json", "dvc.yaml"], project).stdout
    assert set(json.loads(changed)) == {"train@v2t-all", "train@t2v-all"}
    (project / "params.yaml").write_text(yaml.safe_dump(tiny_params(), sort_keys=False))

    # DVC tracks exactly the folders Snakemake writes, with the same files and contents
    lock = yaml.safe_load((project / "dvc.lock").read_text())["stages"]
    lock_outputs = {", ".join(sorted(out["path"] for out in s["outs"])) for s in lock.values()}
    assert lock_outputs == OUTPUTS
    assert data_files(project) == data_files(smk)
    for name, table in output_tables(project).items():
        pd.testing.assert_frame_equal(table, output_tables(smk)[name], obj=name)
    # training is deterministic on CPU, so both tools generate the same pixels
    for path in sorted((project / "data/generated").rglob("*.png")):
        assert path.read_bytes() == (smk / path.relative_to(project)).read_bytes(), path

    # a DVC experiment: -S edits one value, only the stages reading it rerun, `dvc exp show` compares
    run(["git", "add", "-A"], project)
    run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "baseline run"], project)
    ran = run(["dvc", "exp", "run", "-n", "wider_classifier", "-S", "classify.width=0.25"], project).stdout
    assert "Running stage 'classify@visual'" in ran and "Running stage 'train" not in ran
    shown = json.loads(run(["dvc", "exp", "show", "--json"], project).stdout)
    experiments = {e["name"]: e for rev in shown for e in (rev.get("experiments") or [])
                   for e in [e["revs"][0]] if e.get("name")} if shown else {}
    assert "wider_classifier" in experiments
    data = experiments["wider_classifier"]["data"]
    assert data["params"]["params.yaml"]["data"]["classify"]["width"] == 0.25
    assert "reports/metrics.json" in data["metrics"]
    diff = json.loads(run(["dvc", "metrics", "diff", "HEAD", "--json"], project).stdout)
    assert "reports/metrics.json" in diff


def test_snakemake_refuses_config_overrides(snakemake_project):
    project, _ = snakemake_project
    result = subprocess.run(["snakemake", "--cores", "1", "-n", "--config", "roi={'size': 16}"], cwd=project,
                            env=ENV, capture_output=True, text=True)
    assert result.returncode != 0
    assert "params.yaml only" in result.stdout + result.stderr


def test_snakemake_refuses_invalid_params(tmp_path):
    params = tiny_params()
    params["roi"]["unknown_option"] = 1
    project = make_project(tmp_path / "bad", params)
    result = subprocess.run(["snakemake", "--cores", "1", "-n"], cwd=project, env=ENV, capture_output=True, text=True)
    assert result.returncode != 0
    assert "roi: unknown key 'unknown_option'" in result.stdout + result.stderr


def test_per_class_scope_makes_one_training_job_per_class_and_direction(tmp_path):
    params = tiny_params()
    params["translation"]["scope"] = ["all", "denim", "felt"]
    project = make_project(tmp_path / "scoped", params)
    dry = run(["snakemake", "--cores", "2", "-n", "-p"], project).stdout
    trained = set(re.findall(r"output: (models/\S+)", dry))
    assert trained == {f"models/{d}/{s}" for d in ("v2t", "t2v") for s in ("all", "denim", "felt")}
    assert "vtgen train --params params.yaml --direction t2v --scope felt" in dry
    from dvc.repo import Repo

    run(["git", "init", "-q"], project)
    run(["dvc", "init", "-q"], project)
    names = {stage.name for stage in Repo(str(project)).index.stages}
    assert {n for n in names if n.startswith("train@")} == {
        f"train@{d}-{s}" for d in ("v2t", "t2v") for s in ("all", "denim", "felt")}


def test_real_vitac_sample_trains_and_generates_from_unaligned_pairs(tmp_path, vitac_root):
    params = tiny_params(dataset={"source": "vitac", "path": str(vitac_root)},
                         roi={"tactile_box": "auto", "remove_markers": True, "crop_fraction": 1.0})
    project = make_project(tmp_path / "vitac", params)
    run(["snakemake", "--cores", "2"], project)
    for direction in ("v2t", "t2v"):
        summary = json.loads((project / f"models/{direction}/all/train.json").read_text())
        assert summary["training_pairs"] > 0 and summary["aligned_pairs"] == 0  # ViTac views are not aligned
        generated = pd.read_parquet(project / f"data/generated/{direction}/generated.parquet")
        assert (generated["ground_truth_path"] == "").all()  # a random partner is no ground truth
        assert (generated["split"] == "test").sum() == 10  # every test tile of the input modality (10 per folder)
    # scores: set-to-set only (no aligned ground truth); classification needs 2 classes and says so
    scores = json.loads((project / "data/scores/summary.json").read_text())
    assert scores["aligned_pairs"] == {"v2t": 0, "t2v": 0} and scores["synthetic"] is False
    assert scores["scores"]["v2t"]["generated"]["set_colour_ssim"] is not None
    classify = json.loads((project / "data/classify/tactile/summary.json").read_text())
    assert classify["status"].startswith("not applicable")
    report = (project / "reports/summary.md").read_text()
    assert "only the set-to-set protocol applies" in report and "SYNTHETIC" not in report


def test_snakemake_report_collects_the_annotated_outputs(snakemake_project, tmp_path):
    project, _ = snakemake_project
    target = tmp_path / "snakemake_report.html"
    run(["snakemake", "--report", str(target)], project)
    text = target.read_text(errors="replace")
    for category in ("Scores", "Classification", "Report"):
        assert category in text, category
    assert "by_class.csv" in text and "curves.png" in text and "grid_v2t.png" in text
