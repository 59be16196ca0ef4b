"""End-to-end on the tiny configuration: Snakemake and DVC run the same stages and agree; code changes,
kills, deleted outputs and concurrent runs; DVC experiments that compare."""

import json
import math
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import torch
import yaml

from conftest import ENV, REPO, make_project, run, tiny_params

pytestmark = pytest.mark.e2e
STAGES = ["render", "ingest", "roi", "pairs", "settings", "train", "generate", "score", "classify", "report"]
TIMED = ["data/raw/synthetic", "data/ingest", "data/roi", "data/pairs", "models/v2t/all", "models/t2v/all",
         "data/generated/v2t", "data/generated/t2v", "data/scores", "data/classify/visual", "data/classify/tactile"]
REPORT_OUTPUTS = ("reports/figures, reports/index.html, reports/metrics.json, reports/plots/training.csv, "
                  "reports/summary.md, reports/timings.json")
OUTPUTS = {"data/raw/synthetic", "data/ingest", "data/roi", "data/pairs", "data/settings/v2t", "data/settings/t2v", "models/v2t/all", "models/t2v/all",
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
        steps = summary["capacity"]["steps"]  # capacity auto: early stopping may end before the preset's 10
        assert summary["steps"] == steps <= 10 and all(math.isfinite(v) for v in summary["final_losses"].values())
    for folder in TIMED:  # every stage records its wall time beside its output
        assert json.loads((project / folder / "timing.json").read_text())["seconds"] >= 0
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
    # `dvc repro` runs the main job (dvc.yaml) only; the studies' file is not committed (written by --studies)
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
        inputs = {next((d for d in deps if i.startswith(d + "/")), i) for i in job["input"].split(", ")
                  if not i.startswith(".vtgen/params/")}  # Snakemake's record of the params DVC tracks itself
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
    assert set(json.loads(changed)) == {"settings@v2t", "settings@t2v"}  # whose files training depends on
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


def test_plain_dvc_status_on_a_fresh_clone_names_the_main_job_only(tmp_path, default_params):
    """DVC reads every dvc.yaml in the repository, so the studies' pipeline is not committed: plain `dvc status`
    names the main job's stages only; `vtgen workflow --studies` writes the studies' file for DVC (issue 25)."""
    import os

    from vtgen.pipeline import stages

    clone = tmp_path / "clone"  # the tracked files of the working tree, as a fresh clone has them
    listed = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, text=True, check=True).stdout
    for name in filter(None, listed.split("\0")):
        source, target = REPO / name, clone / name
        target.parent.mkdir(parents=True, exist_ok=True)
        if source.is_symlink():
            os.symlink(os.readlink(source), target)
        elif source.is_file():
            shutil.copy2(source, target)
    assert (clone / ".dvc/config").is_file()  # the DVC project is part of what is committed
    run(["git", "init", "-q"], clone)
    main = {s.name for s in stages(default_params, "main")}
    studies = {s.name for s in stages(default_params, "studies")}

    def listed_stages(*target: str) -> set[str]:  # base names of the stages `dvc status` lists
        status = json.loads(run(["dvc", "status", "--json", *target], clone).stdout or "{}")
        return {key.rsplit(":", 1)[-1].split("@")[0] for key in status}

    assert listed_stages() == main  # a fresh clone has no outputs: every main stage, and nothing else
    env = {**ENV, "PYTHONPATH": str(clone / "src")}  # code dependencies are paths inside the clone
    subprocess.run([sys.executable, "-m", "vtgen", "workflow", "--studies"], cwd=clone, env=env, check=True,
                   capture_output=True)
    assert listed_stages("workflow/studies/dvc.yaml") == studies


def test_real_vitac_sample_trains_and_generates_from_unaligned_pairs(tmp_path, vitac_root):
    params = tiny_params(dataset={"source": "vitac", "path": str(vitac_root)},
                         roi={"tactile_box": "auto", "remove_markers": True, "crop_fraction": 1.0})
    project = make_project(tmp_path / "vitac", params)
    run(["snakemake", "--cores", "2"], project)
    for direction in ("v2t", "t2v"):
        summary = json.loads((project / f"models/{direction}/all/train.json").read_text())
        assert summary["training_pairs"] > 0 and summary["aligned_pairs"] == 0  # ViTac views are not aligned
        assert direction == "t2v" or summary["conditioning"] == "none"  # one cloth: no class to read (auto)
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


def test_real_vt60_subset_in_its_own_layout_runs_the_whole_main_job(tmp_path, vt60_root):
    """A researcher's own data: 10 objects, grey 640x480 round-sensor frames beside 300x300 photos,
    described by a path pattern; instances are the split groups; translation by class pairs."""
    params = tiny_params(dataset={"source": "pattern", "path": str(vt60_root),
                                  "pattern": "{modality}/{class}/{instance}/{name}.jpg"},
                         roi={"tactile_box": "auto"})
    project = make_project(tmp_path / "vt60", params)
    run(["snakemake", "--cores", "2"], project)
    ingest = json.loads((project / "data/ingest/summary.json").read_text())
    assert len(ingest["classes"]) == 10 and ingest["kept"] == 720
    assert ingest["duplicates"]["near_duplicate_files"] > 0  # consecutive frames of one grasp
    # instances are the unit of splitting: each (class, instance) lies in one split, with both modalities
    splits = pd.read_parquet(project / "data/pairs/splits.parquet")
    manifest = pd.read_parquet(project / "data/ingest/manifest.parquet")
    instance = {p: Path(p).parent.name for p in manifest["path"]}
    image_of = pd.read_parquet(project / "data/roi/tiles.parquet")
    splits["instance"] = [instance[p] for p in image_of["image_path"]]
    assert (splits.groupby(["class", "instance"])["split"].nunique() == 1).all()
    assert set(splits["split"]) >= {"train", "test"}
    roi = json.loads((project / "data/roi/summary.json").read_text())
    assert roi["channels"]["tactile"] == 1 and roi["regions"]["tactile"].get("disc", 0) >= 470
    for direction in ("v2t", "t2v"):
        pairs = pd.read_parquet(project / f"data/pairs/{direction}.parquet")
        assert (pairs["pair_kind"] == "class").all()  # no touch frame is aligned with a photo
    told = json.loads((project / "models/v2t/all/train.json").read_text())
    assert (told["conditioning_setting"], told["conditioning"]) == ("auto", "inferred")  # class pairs: read the photo
    assert told["input_reader"] == "features"
    for modality in ("visual", "tactile"):
        classify = json.loads((project / f"data/classify/{modality}/summary.json").read_text())
        assert classify["status"] == "ok" and len(classify["classes"]) == 10
        assert classify["settings"]["real"]["interval"] is not None
    scores = json.loads((project / "data/scores/summary.json").read_text())
    assert scores["distribution"]["t2v"]["ssim_name"] == "Colour-SSIM" and scores["distribution"]["v2t"]["ssim_name"] == "SSIM"
    assert scores["verdicts"] and scores["synthetic"] is False
    report = (project / "reports/summary.md").read_text()
    assert "SYNTHETIC" not in report and "only the set-to-set protocol applies" in report


def test_a_tactile_only_folder_runs_what_applies_and_says_why_there_is_no_translation(tmp_path, vt60_root):
    params = tiny_params(dataset={"source": "pattern", "path": str(vt60_root / "touch"),
                                  "pattern": "{class}/{instance}/{name}.jpg", "modality": "tactile"},
                         roi={"tactile_box": "auto"})
    project = make_project(tmp_path / "touch", params)
    run(["snakemake", "--cores", "2"], project)
    for direction in ("v2t", "t2v"):
        train = json.loads((project / f"models/{direction}/all/train.json").read_text())
        assert train["status"].startswith("not applicable") and not (project / f"models/{direction}/all/generator.pt").exists()
    tactile = json.loads((project / "data/classify/tactile/summary.json").read_text())
    assert tactile["status"] == "ok" and len(tactile["classes"]) == 10 and tactile["skipped"]  # no generated images
    visual = json.loads((project / "data/classify/visual/summary.json").read_text())
    assert visual["status"].startswith("not applicable")
    assert json.loads((project / "data/scores/summary.json").read_text())["not_scored"].keys() == {"v2t", "t2v"}
    report = (project / "reports/summary.md").read_text()
    assert "translation needs both modalities and the data has only tactile images" in report


# ---------------------------------------------------------------------------------------------
# Caches that know the code, and runs that heal

def finished_copy(snakemake_project, where: Path) -> tuple[Path, dict]:
    """A copy of the finished tiny project, recorded by DVC too, whose commands run its own copy of
    the package (PYTHONPATH), so a test can change the code; returns it and its environment."""
    source, _ = snakemake_project
    project = where / "project"
    shutil.copytree(source, project, symlinks=True, ignore=shutil.ignore_patterns("locks", "incomplete", "__pycache__"))
    shutil.copy(REPO / ".gitignore", project / ".gitignore")
    env = {**ENV, "PYTHONPATH": str(project / "src")}
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    for command in (["git", "init", "-q"], ["dvc", "init", "-q"], ["dvc", "config", "core.analytics", "false"],
                    ["dvc", "commit", "-f", "--with-deps", "report"], ["git", "add", "-A"],
                    git + ["commit", "-qm", "finished run"]):  # dvclive, in the train stage, needs a commit
        subprocess.run(command, cwd=project, env=env, check=True, capture_output=True)
    return project, env


def planned(project: Path, env: dict) -> tuple[set[str], set[str]]:
    """(jobs `snakemake -n` would run, stages `dvc status` of the main job names)."""
    dry = subprocess.run(["snakemake", "-n"], cwd=project, env=env, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stdout[-3000:] + dry.stderr[-3000:]
    jobs = set()
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", dry.stdout):
        head = re.match(r"(?:local)?rule (\w+):", block)
        if head:
            wildcards = re.search(r"^\s+wildcards: (.*)$", block, flags=re.M)
            jobs.add(head[1] + ("@" + "-".join(w.split("=", 1)[1] for w in wildcards[1].split(", ")) if wildcards else ""))
    status = subprocess.run(["dvc", "status", "--json", "report", "--with-deps"], cwd=project, env=env,
                            capture_output=True, text=True, check=True)
    return jobs, set(json.loads(status.stdout))


def weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)["state_dict"]


def test_a_change_to_the_model_code_retrains_and_reruns_everything_after_in_both_tools(snakemake_project, tmp_path):
    project, env = finished_copy(snakemake_project, tmp_path)
    before = weights(project / "models/v2t/all/generator.pt")
    models = project / "src/vtgen/core/models.py"
    models.write_text(models.read_text().replace("nn.LeakyReLU(0.2)", "nn.LeakyReLU(0.3)"))
    jobs, changed = planned(project, env)
    reading_models = {"train@v2t-all", "train@t2v-all", "generate@v2t", "generate@t2v", "classify@visual",
                      "classify@tactile"}
    assert reading_models <= changed and "score" not in changed  # score's code does not import the networks
    assert jobs == reading_models | {"score", "report", "all"}
    rerun = subprocess.run(["snakemake", "--cores", "2"], cwd=project, env=env, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stdout[-3000:] + rerun.stderr[-3000:]
    assert "code that defines training changed" in rerun.stdout + rerun.stderr
    assert json.loads((project / "models/v2t/all/timing.json").read_text())["resumed_from_step"] == 0
    after = weights(project / "models/v2t/all/generator.pt")
    assert any(not torch.equal(before[k], after[k]) for k in before)  # trained afresh, not the old model


def test_a_comment_in_one_stage_module_reruns_only_that_stage_and_what_follows(snakemake_project, tmp_path):
    project, env = finished_copy(snakemake_project, tmp_path)
    score = project / "src/vtgen/stages/score.py"
    score.write_text(score.read_text() + "\n# a comment\n")
    jobs, changed = planned(project, env)
    assert changed == {"score"}
    assert jobs == {"score", "report", "all"}


def wait_for(path: Path, process: subprocess.Popen, seconds: float = 300) -> None:
    deadline = time.monotonic() + seconds
    while not path.exists():
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"{path} did not appear:\n{process.communicate()[0][-3000:]}")
        time.sleep(0.05)


def test_a_killed_run_and_a_deleted_output_heal_with_one_plain_rerun(snakemake_project, tmp_path):
    reference, _ = snakemake_project
    project = make_project(tmp_path / "project", tiny_params())
    snakemake = subprocess.Popen(["snakemake", "--cores", "2"], cwd=project, env=ENV, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True)
    wait_for(project / "data/pairs", snakemake)
    snakemake.send_signal(signal.SIGKILL)  # Snakemake itself: its lock and its running jobs are left behind
    snakemake.communicate()
    run(["snakemake", "--cores", "2"], project)  # no --unlock
    for path in sorted((reference / "data/generated").rglob("*.png")):
        assert path.read_bytes() == (project / path.relative_to(reference)).read_bytes(), path

    shutil.rmtree(project / "data/pairs")
    jobs = set(re.findall(r"^rule (\w+):", run(["snakemake", "-n"], project).stdout, flags=re.M))
    assert jobs == {"pairs", "settings", "train", "generate", "score", "classify", "report", "all"}  # settings reads pairs
    run(["snakemake", "--cores", "2"], project)
    assert (project / "data/pairs/v2t.parquet").is_file()
    assert "Nothing to be done" in run(["snakemake", "-n"], project).stdout


def test_snakemake_and_dvc_runs_exclude_each_other(tmp_path):
    project = make_project(tmp_path / "project", tiny_params())
    holder = subprocess.Popen([sys.executable, "-c", "import time; from vtgen.io.runlock import hold_run_lock; "
                               "hold_run_lock('dvc repro'); print('held', flush=True); time.sleep(120)"],
                              cwd=project, env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        smk = subprocess.run(["snakemake", "--cores", "1", "data/raw/synthetic"], cwd=project, env=ENV,
                             capture_output=True, text=True)
        assert smk.returncode != 0 and "another run of this project is in progress (dvc repro" in smk.stdout + smk.stderr
        planned = subprocess.run(["snakemake", "-n"], cwd=project, env=ENV, capture_output=True, text=True)
        assert "in progress (dvc repro, pid" in planned.stderr  # no job is started, yet the run says outputs went unchecked
        assert "outputs are not checked" in planned.stderr
        stage = subprocess.run(["vtgen", "render", "--out", "data/raw/synthetic"], cwd=project, env=ENV,
                               capture_output=True, text=True)
        assert stage.returncode == 2 and "another run of this project is in progress" in stage.stderr
        assert not (project / "data/raw/synthetic").exists()
    finally:
        holder.kill()
        holder.wait()
    run(["snakemake", "--cores", "1", "data/raw/synthetic"], project)  # the lock went with its holder


# ---------------------------------------------------------------------------------------------
# DVC experiments that compare

def numbers(tree) -> list[float]:
    if isinstance(tree, dict):
        return [n for value in tree.values() for n in numbers(value)]
    return [tree] if isinstance(tree, (int, float)) and not isinstance(tree, bool) else []


def test_dvc_experiments_show_compare_apply_and_round_trip(snakemake_project, tmp_path):
    project, _ = finished_copy(snakemake_project, tmp_path)  # the baseline: the finished run, committed in git and DVC
    tracked = run(["git", "ls-files"], project).stdout.split()
    assert {"dvc.lock", "reports/metrics.json", "reports/plots/training.csv"} <= set(tracked)

    run(["dvc", "exp", "run", "-n", "one_epoch", "-S", "classify.epochs=1"], project)
    run(["dvc", "exp", "run", "-n", "three_epochs", "-S", "classify.epochs=3"], project)
    shown = json.loads(run(["dvc", "exp", "show", "--json"], project).stdout)
    rows = {"baseline": shown[0]["data"]} if shown and shown[0].get("data") else {}
    for baseline in shown:
        for experiment in baseline.get("experiments") or []:
            rows[experiment["name"]] = experiment["revs"][0]["data"]
    assert {"baseline", "one_epoch", "three_epochs"} <= set(rows)
    for name, data in rows.items():
        assert len(numbers(data["metrics"]["reports/metrics.json"]["data"])) >= 4, name
    assert rows["one_epoch"]["params"]["params.yaml"]["data"]["classify"]["epochs"] == 1
    diff = json.loads(run(["dvc", "metrics", "diff", "one_epoch", "three_epochs", "--json"], project).stdout)
    assert diff.get("reports/metrics.json")
    run(["dvc", "plots", "diff", "one_epoch", "three_epochs", "--json"], project)

    run(["dvc", "exp", "apply", "one_epoch"], project)
    assert "up to date" in run(["dvc", "status", "dvc.yaml"], project).stdout.lower()
    applied = json.loads((project / "reports/metrics.json").read_text())
    assert numbers(applied) == numbers(rows["one_epoch"]["metrics"]["reports/metrics.json"]["data"])

    run(["dvc", "remote", "add", "-d", "local", str(tmp_path / "remote")], project)
    run(["dvc", "push"], project)
    for folder in ("data", "models", ".dvc/cache", "reports/figures"):
        shutil.rmtree(project / folder)
    run(["dvc", "pull"], project)
    assert "up to date" in run(["dvc", "status", "dvc.yaml"], project).stdout.lower()
    assert (project / "reports/index.html").is_file() and (project / "models/v2t/all/generator.pt").is_file()


def test_render_refuses_a_params_file_for_another_dataset_and_names_the_fix(tmp_path, capsys, monkeypatch):
    """DVC runs the stages of dvc.yaml as written: one written for the synthetic dataset still lists render after
    params.yaml moves to the user's data. Rendering 720 unused samples would pass silently; the stage says
    how to rewrite dvc.yaml instead, and writes nothing."""
    from vtgen.cli import main

    monkeypatch.chdir(tmp_path)  # a project of its own (its own run lock)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    (tmp_path / "mine").mkdir()
    params["dataset"] = dict(params["dataset"], source="generic", path=str(tmp_path / "mine"))
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    out = tmp_path / "data" / "raw" / "synthetic"
    assert main(["render", "--params", str(tmp_path / "params.yaml"), "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "dataset.source is 'generic'" in error and "`vtgen workflow`" in error
    assert not out.exists()
