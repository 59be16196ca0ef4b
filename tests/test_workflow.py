"""End-to-end: Snakemake and DVC run the data stages on a tiny configuration and agree."""

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from conftest import REPO, tiny_params

pytestmark = pytest.mark.e2e
BIN = str(Path(sys.executable).parent)
ENV = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "DVC_NO_ANALYTICS": "1"}
STAGES = ["render", "ingest", "roi", "pairs"]


def make_project(where: Path, params: dict) -> Path:
    """A copy of the workflow files with ``params`` as its params.yaml."""
    where.mkdir(parents=True)
    for name in ("Snakefile", "dvc.yaml", ".dvcignore"):
        shutil.copy(REPO / name, where / name)
    for name in ("workflow", "src"):
        shutil.copytree(REPO / name, where / name, ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    (where / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return where


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess:
    result = subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True)
    assert result.returncode == 0, f"{' '.join(cmd)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


def output_tables(project: Path) -> dict[str, pd.DataFrame]:
    return {
        name: pd.read_parquet(project / name)
        for name in ("data/ingest/manifest.parquet", "data/roi/tiles.parquet",
                     "data/pairs/v2t.parquet", "data/pairs/t2v.parquet", "data/pairs/splits.parquet")
    }


def data_files(project: Path) -> set[str]:
    return {str(p.relative_to(project)) for p in (project / "data").rglob("*") if p.is_file() and p.name not in (".gitignore", ".snakemake_timestamp")}


@pytest.fixture(scope="module")
def snakemake_project(tmp_path_factory):
    project = make_project(tmp_path_factory.mktemp("smk") / "project", tiny_params())
    result = run(["snakemake", "--cores", "2"], project)
    return project, result


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
    for stage in STAGES:
        assert (project / "logs/benchmarks" / f"{stage}.tsv").is_file()
    # a finished workflow has nothing left to do
    again = run(["snakemake", "--cores", "2", "-n"], project)
    assert "Nothing to be done" in again.stdout + again.stderr


def test_snakemake_and_dvc_run_the_same_commands_and_outputs(snakemake_project, tmp_path):
    smk, _ = snakemake_project
    project = make_project(tmp_path / "dvc", tiny_params())
    run(["git", "init", "-q"], project)
    run(["dvc", "init", "-q"], project)
    run(["dvc", "config", "core.analytics", "false"], project)
    run(["dvc", "repro"], project)
    assert "up to date" in run(["dvc", "status"], project).stdout.lower()

    # the same command, inputs and outputs per stage
    dry = run(["snakemake", "--cores", "2", "-n", "-p", "--forceall"], smk).stdout
    rules = {m["rule"]: m for m in re.finditer(
        r"rule (?P<rule>\w+):\n    input: (?P<input>[^\n]*)\n    output: (?P<output>[^\n]*)\n.*?Shell command: (?P<cmd>[^\n]*)",
        dry, flags=re.S)}
    stages = yaml.safe_load((project / "dvc.yaml").read_text())["stages"]
    assert sorted(stages) == sorted(rules) == sorted(STAGES)
    params = tiny_params()
    for name, stage in stages.items():
        deps = {d.replace("${dataset.path}", params["dataset"]["path"]) for d in stage["deps"]}
        assert stage["cmd"] == rules[name]["cmd"], name
        assert deps == set(rules[name]["input"].split(", ")), name
        assert set(stage["outs"]) == set(rules[name]["output"].split(", ")), name

    # DVC tracks exactly the folders Snakemake writes, with the same files and contents
    lock = yaml.safe_load((project / "dvc.lock").read_text())["stages"]
    assert {out["path"] for s in lock.values() for out in s["outs"]} == {
        "data/raw/synthetic", "data/ingest", "data/roi", "data/pairs"}
    assert data_files(project) == data_files(smk)
    for name, table in output_tables(project).items():
        pd.testing.assert_frame_equal(table, output_tables(smk)[name], obj=name)


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
