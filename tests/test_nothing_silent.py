"""Issue 25, nothing silent: every case ends clean (healed identical to an undamaged run, or refused with one
line naming the file or key, nothing lost), and Snakemake and DVC agree on what is up to date both ways.

One finished tiny project in a git and DVC repository serves the cases in order (a Snakemake run in it, a
refused `dvc repro`, damaged outputs healed, `dvc pull` into an empty workspace); a tiny pattern dataset
serves the changes below ``dataset.path`` (the ingest job only); the training limits run `vtgen train` on the
session project's pairs.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

from conftest import ENV, REPO, make_project, run, tiny_params, write_jpegs
from test_reliability import same_weights, snapshot
from vtgen import cli
from vtgen.pipeline import dvc_yaml

pytestmark = pytest.mark.e2e

OUTPUTS = ("data/raw/synthetic", "data/ingest", "data/roi", "data/pairs", "models/v2t/all", "models/t2v/all",
           "data/generated/v2t", "data/generated/t2v", "data/scores", "data/classify/visual", "data/classify/tactile",
           "reports")
# the files that record wall times: each stage's timing.json, and the classify, score and report stages' outputs
# (their summaries and tables give the seconds of their parts); every other output is data, the same in two runs
TIMED = ("timing.json", ".snakemake_timestamp")
TIMED_STAGES = ("reports/", "data/classify/", "data/scores/")


def outputs_snapshot(project: Path) -> dict[str, str]:
    """Output file -> md5 (Snakemake's empty folder markers left out: they are not data, and DVC ignores them)."""
    return {f"{out}/{name}": md5 for out in OUTPUTS for name, md5 in snapshot(project / out).items()
            if Path(name).name != ".snakemake_timestamp"}


def deterministic(files: dict[str, str]) -> dict[str, str]:
    """The files two runs of the same code write byte for byte: data, tiles, pairs, summaries, training records and
    logs, generated images, content records (weights are compared by value; classify, score and the report are
    compared by their file lists)."""
    return {k: v for k, v in files.items() if Path(k).name not in TIMED and not k.endswith("generator.pt")
            and not k.startswith(TIMED_STAGES)}


def without_times(files: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in files.items() if Path(k).name != "timing.json"}


def dvc_changed(project: Path) -> dict:
    return json.loads(run(["dvc", "status", "--json", "dvc.yaml"], project).stdout)


def planned(project: Path, *target: str) -> tuple[set[str], str]:
    dry = run(["snakemake", "-n", *target], project)
    return set(re.findall(r"^(?:local)?rule (\w+):", dry.stdout, flags=re.M)), dry.stdout + dry.stderr


@pytest.fixture(scope="module")
def dvc_run(snakemake_project, tmp_path_factory):
    """A copy of the finished tiny project in a git and DVC repository, and the result of a Snakemake run in it
    after one value changed (score.batch_size: score and report run again)."""
    source, _ = snakemake_project
    project = tmp_path_factory.mktemp("silent") / "project"
    shutil.copytree(source, project, symlinks=True, ignore=shutil.ignore_patterns("locks", "incomplete"))
    shutil.copy(REPO / ".gitignore", project / ".gitignore")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    for command in (["git", "init", "-q"], ["dvc", "init", "-q"], ["dvc", "config", "core.analytics", "false"],
                    ["git", "add", "-A"], git + ["commit", "-qm", "project"]):
        run(command, project)
    params = yaml.safe_load((project / "params.yaml").read_text())
    params["score"]["batch_size"] = 64
    (project / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    return project, run(["snakemake", "--cores", "2"], project)


def test_a_snakemake_run_in_a_dvc_project_leaves_dvc_up_to_date(dvc_run):
    project, result = dvc_run
    assert "finished stages recorded in DVC's cache (dvc commit" in result.stderr
    assert dvc_changed(project) == {}  # `dvc repro` would redo nothing


def test_a_dvc_repro_refused_by_the_run_lock_removes_no_output(dvc_run):
    project, _ = dvc_run
    before = outputs_snapshot(project)
    params_text = (project / "params.yaml").read_text()
    params = yaml.safe_load(params_text)
    params["classify"]["epochs"] = 3  # classify, score and report would rerun
    (project / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    holder = subprocess.Popen([sys.executable, "-c", "import time; from vtgen.io.runlock import hold_run_lock; "
                               "hold_run_lock('snakemake'); print('held', flush=True); time.sleep(120)"],
                              cwd=project, env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        refused = subprocess.run(["dvc", "repro"], cwd=project, env=ENV, capture_output=True, text=True)
    finally:
        holder.kill()
        holder.wait()
        (project / "params.yaml").write_text(params_text)
    assert refused.returncode != 0
    assert "another run of this project is in progress (snakemake" in refused.stdout + refused.stderr
    assert outputs_snapshot(project) == before  # DVC removed nothing before the lock refused it
    assert dvc_changed(project) == {}


def test_damaged_outputs_are_named_and_rebuilt_identical_to_the_undamaged_run(dvc_run):
    project, _ = dvc_run
    before = outputs_snapshot(project)
    v2t_model = project / "tmp_v2t_generator.pt"
    shutil.copy(project / "models/v2t/all/generator.pt", v2t_model)
    tile = sorted((project / "data/roi/tiles/visual").rglob("*.png"))[0]
    damaged = {"models/v2t/all/generator.pt": "train@v2t-all", "reports/metrics.json": "report",
               "data/pairs/v2t.parquet": "pairs", str(tile.relative_to(project)): "roi"}
    for path in damaged:
        with open(project / path, "r+b") as handle:
            handle.truncate(10)
    jobs, text = planned(project)
    for path, job in damaged.items():
        assert re.search(rf"^vtgen: {re.escape(job)}: {re.escape(path)} has 10 bytes, \d+ when written; it runs again$",
                         text, flags=re.M), (path, text[-3000:])
    assert jobs == {"roi", "pairs", "settings", "train", "generate", "score", "classify", "report", "all"}  # settings reads pairs

    rebuilt = run(["snakemake", "--cores", "2"], project)
    # training's data is unchanged, so each direction's finished checkpoint is its result: nothing is trained again
    assert (rebuilt.stdout + rebuilt.stderr).count("its result is used, nothing is trained") == 2, "\n".join(l for l in (rebuilt.stdout + rebuilt.stderr).splitlines() if "train" in l)
    after = outputs_snapshot(project)
    assert after.keys() == before.keys()
    assert deterministic(after) == deterministic(before)
    assert same_weights(project / "models/v2t/all/generator.pt", v2t_model)
    assert "Nothing to be done" in planned(project)[1]
    assert dvc_changed(project) == {}


def test_after_dvc_pull_into_an_empty_workspace_snakemake_has_nothing_to_do(dvc_run, tmp_path):
    project, _ = dvc_run
    before = outputs_snapshot(project)
    run(["dvc", "remote", "add", "-d", "local", str(tmp_path / "remote")], project)
    run(["dvc", "push"], project)
    for folder in ("data", "models", "reports/figures", ".dvc/cache", ".snakemake", ".vtgen"):
        shutil.rmtree(project / folder)
    for name in ("index.html", "summary.md", "timings.json"):
        (project / "reports" / name).unlink()
    run(["dvc", "pull"], project)
    after = outputs_snapshot(project)
    assert without_times(after) == without_times(before)
    assert not any(Path(k).name == "timing.json" for k in after)  # a run's times stay with that run: DVC ignores them
    jobs, text = planned(project)
    assert "Nothing to be done" in text, text[-3000:]
    assert dvc_changed(project) == {}


# ---------------------------------------------------------------------------------------------
# Changes below dataset.path: by content, not the top folder's time (the ingest job only)

@pytest.fixture
def pattern_project(tmp_path):
    data = write_jpegs(tmp_path / "dataset", 16)  # c0, c1 / visual, tactile / s00000.jpg ...
    params = tiny_params(dataset={"source": "pattern", "path": str(data), "pattern": "{class}/{modality}/{name}.jpg"})
    project = make_project(tmp_path / "project", params)
    run(["snakemake", "--cores", "1", "data/ingest"], project)
    return project, data


def manifest_paths(project: Path) -> set[str]:
    return {Path(p).name for p in pd.read_parquet(project / "data/ingest/manifest.parquet")["path"]}


def test_images_added_replaced_or_deleted_below_dataset_path_rerun_ingest(pattern_project):
    project, data = pattern_project
    assert len(manifest_paths(project)) == 16
    top = os.stat(data).st_mtime_ns
    folder = data / "c0" / "visual"
    old = folder / "s00000.jpg"

    def changes_ingest(expected: set[str]) -> None:
        assert os.stat(data).st_mtime_ns == top  # the top folder's time did not change
        jobs, text = planned(project, "data/ingest")
        assert jobs == {"ingest"}, text[-2000:]
        assert f"vtgen: ingest: input {data} changed since it ran" in text
        run(["snakemake", "--cores", "1", "data/ingest"], project)
        assert manifest_paths(project) == expected
        assert "Nothing to be done" in planned(project, "data/ingest")[1]

    expected = manifest_paths(project)
    shutil.copy(old, folder / "added_1.jpg")  # new files in a subfolder (exact duplicates are still images)
    shutil.copy(folder / "s00004.jpg", folder / "added_2.jpg")
    changes_ingest(expected | {"added_1.jpg", "added_2.jpg"})

    shutil.copy(folder / "s00008.jpg", old)  # replaced in place: other bytes, same name and size; no folder time changes
    assert old.stat().st_size == (folder / "s00008.jpg").stat().st_size
    changes_ingest(expected | {"added_1.jpg", "added_2.jpg"})
    md5 = pd.read_parquet(project / "data/ingest/manifest.parquet").set_index("path")["md5"]
    assert md5[str(old)] == md5[str(folder / "s00008.jpg")]  # the manifest has the new bytes

    (folder / "added_2.jpg").unlink()
    changes_ingest(expected | {"added_1.jpg"})


def test_a_dvc_yaml_written_for_another_source_is_named_and_not_committed_against(pattern_project):
    """A user who switched dataset.source without `vtgen workflow` keeps the synthetic dvc.yaml (it lists render):
    the Snakemake run says so at its start and end and records nothing in DVC, where it used to commit its stages
    against the wrong dvc.yaml; after `vtgen workflow` the next run records them and DVC agrees."""
    project, data = pattern_project
    shutil.copy(REPO / ".gitignore", project / ".gitignore")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    for command in (["git", "init", "-q"], ["dvc", "init", "-q"], ["dvc", "config", "core.analytics", "false"],
                    ["git", "add", "-A"], git + ["commit", "-qm", "project"]):
        run(command, project)
    folder = data / "c0" / "visual"
    shutil.copy(folder / "s00000.jpg", folder / "added_1.jpg")  # ingest runs again
    stale = run(["snakemake", "--cores", "1", "data/ingest"], project).stderr
    warning = ("vtgen: warning: dvc.yaml lists render, which these params do not have (dataset.source is 'pattern'), "
               "so `dvc status` and `dvc exp run` would not follow this run: run `vtgen workflow` to rewrite it")
    assert stale.count(warning) == 2, stale[-3000:]  # at the start, and at the end instead of `dvc commit`
    assert "nothing was recorded" in stale and "recorded in DVC's cache" not in stale
    assert not (project / "dvc.lock").exists()

    params = yaml.safe_load((project / "params.yaml").read_text())
    (project / "dvc.yaml").write_text(dvc_yaml(params, "main"))  # what `vtgen workflow` writes (run from the project)
    shutil.copy(folder / "s00004.jpg", folder / "added_2.jpg")
    written = run(["snakemake", "--cores", "1", "data/ingest"], project).stderr
    assert "warning: dvc.yaml" not in written and "1 finished stages recorded in DVC's cache" in written, written[-3000:]
    assert "ingest" not in json.loads(run(["dvc", "status", "--json", "ingest"], project).stdout)


# ---------------------------------------------------------------------------------------------
# Training limits: checked before they are hit

def train(project: Path, tmp_path: Path, capsys, **preset) -> tuple[int, str, str]:
    """`vtgen train` (v2t, all) in ``project`` with ``preset`` values, writing its model and checkpoints under
    ``tmp_path``."""
    params = yaml.safe_load((project / "params.yaml").read_text())
    params["presets"]["fast"].update(preset)
    params["translation"]["capacity"]["mode"] = "fixed"
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    code = cli.main(["train", "--params", str(path), "--direction", "v2t", "--scope", "all", "--pairs",
                     str(project / "data/pairs"), "--out", str(tmp_path / "model"), "--checkpoints",
                     str(tmp_path / "checkpoints")])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_batch_larger_than_the_training_data_is_capped_with_a_message(snakemake_project, tmp_path, capsys,
                                                                         monkeypatch):
    project, _ = snakemake_project
    monkeypatch.chdir(project)  # the pair table names tiles relative to the project
    code, out, err = train(project, tmp_path, capsys, batch_size=100000, iterations=2)
    assert code == 0, err
    pairs = json.loads((tmp_path / "model/train.json").read_text())["training_pairs"]
    assert f"train v2t/all: presets.fast.batch_size 100000 is larger than the {pairs} training pairs; using batch " \
           f"{pairs}" in out


def test_a_training_step_that_would_not_fit_in_memory_is_refused_before_it_starts(snakemake_project, tmp_path,
                                                                                  capsys, monkeypatch):
    project, _ = snakemake_project
    monkeypatch.chdir(project)
    code, out, err = train(project, tmp_path, capsys, ngf=4096, ndf=4096)
    assert code == 2
    assert re.fullmatch(r"vtgen train: error: presets\.fast: a training step at batch 2, 32 px and width 4096 needs "
                        r"about [\d.]+ GB, more than the [\d.]+ GB of memory available; lower presets\.fast\.batch_size, "
                        r"size, ngf or ndf\n", err), err
    assert not (tmp_path / "model").exists() and not (tmp_path / "checkpoints").exists()
