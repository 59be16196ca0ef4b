"""Faults: stages killed part-way, a full disk, unwritable folders, the DVC remote round trip, and
the SLURM profile's plan.

Tiny configurations (conftest.tiny_params) keep every run to seconds. The stage commands run in
subprocesses where a real SIGKILL is the point, and in this process where a monkeypatched
failure is (a full disk).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from conftest import ENV, REPO, make_project, run, tiny_params
from vtgen import cli
from vtgen.io.timing import read_with_times
from vtgen.io.images import atomic_output_dir, describe_os_error, OutputDirError

pytestmark = pytest.mark.e2e


def snapshot(folder: Path) -> dict[str, str]:
    """relative path -> md5 of every file below ``folder``."""
    return {str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def data_only(files: dict[str, str]) -> dict[str, str]:
    """Leave out timing.json: a run's times, not data, which DVC neither hashes nor caches (.dvcignore)."""
    return {k: v for k, v in files.items() if Path(k).name != "timing.json"}


def stable(files: dict[str, str]) -> dict[str, str]:
    """Leave out the wall times (timing.json: the only output file that holds any) and checkpoint-format bytes
    (weights are compared by value)."""
    return {k: v for k, v in files.items() if Path(k).name not in ("generator.pt", "timing.json")}


def same_weights(a: Path, b: Path) -> bool:
    first, second = (torch.load(p, map_location="cpu", weights_only=False)["state_dict"] for p in (a, b))
    return first.keys() == second.keys() and all(torch.equal(first[k], second[k]) for k in first)


def cli_error(argv: list[str], capsys) -> tuple[int, str]:
    code = cli.main(argv)
    return code, capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# One DVC project with the data stages, V2T training and V2T generation done: the round trip
# through a DVC remote, then each stage killed part-way and run again.

@pytest.fixture(scope="module")
def dvc_project(tmp_path_factory) -> Path:
    # render in this process (workers 1) so that a test can kill it between two image writes
    project = make_project(tmp_path_factory.mktemp("dvc") / "project", tiny_params(synthetic={"workers": 1}))
    run(["git", "init", "-q"], project)
    run(["dvc", "init", "-q"], project)
    run(["dvc", "config", "core.analytics", "false"], project)
    run(["git", "add", "-A"], project)
    run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "project"], project)
    run(["dvc", "repro", "generate@v2t"], project)
    return project


def test_dvc_push_then_pull_into_an_empty_workspace_and_cache_restores_every_output(dvc_project, tmp_path):
    project = dvc_project
    lock = yaml.safe_load((project / "dvc.lock").read_text())["stages"]
    outs = sorted(out["path"] for stage in lock.values() for out in stage["outs"])
    assert outs == ["data/generated/v2t", "data/ingest", "data/pairs", "data/raw/synthetic", "data/roi", "data/settings/v2t",
                    "models/v2t/all"]
    before = {out: snapshot(project / out) for out in outs}
    status = ["dvc", "status", "generate@v2t", "--with-deps", "--json"]
    assert json.loads(run(status, project).stdout) == {}

    run(["dvc", "remote", "add", "-d", "local", str(tmp_path / "remote")], project)
    run(["dvc", "push", "generate@v2t", "--with-deps"], project)
    assert json.loads(run(["dvc", "status", "--cloud", "--json"], project).stdout) == {}  # the remote has it all

    for out in outs:
        shutil.rmtree(project / out)
    shutil.rmtree(project / ".dvc" / "cache")
    gone = json.loads(run(status, project).stdout)
    assert set(gone) == {"render", "ingest", "roi", "pairs", "settings@v2t", "train@v2t-all", "generate@v2t"}  # DVC sees them missing

    run(["dvc", "pull", "generate@v2t", "--with-deps"], project)
    assert json.loads(run(status, project).stdout) == {}
    restored = {out: snapshot(project / out) for out in outs}
    assert {out: data_only(files) for out, files in restored.items()} == {out: data_only(files) for out, files in before.items()}
    assert not any("timing.json" in files for files in restored.values())  # a run's times stay with that run


# A small driver: run a vtgen command, and SIGKILL the process itself right after the N-th call of
# one function (an image write, a table write, the rename that replaces the old output). No
# cleanup runs, exactly as when the machine or the scheduler kills the job.
KILLER = """
import importlib, os, signal, sys, threading
target, at = sys.argv[1], int(sys.argv[2])
module, _, attribute = target.partition(":")
owner = importlib.import_module(module)
*parents, name = attribute.split(".")
for part in parents:
    owner = getattr(owner, part)
original, calls, lock = getattr(owner, name), [0], threading.Lock()
stage = os.getpid()  # the stage's process: a worker process forked from it (roi) kills the stage, not itself
def wrapper(*args, **kwargs):
    result = original(*args, **kwargs)
    with lock:
        calls[0] += 1
        if calls[0] == at:
            os.kill(stage, signal.SIGKILL)
            if os.getpid() != stage:
                os._exit(1)  # as the worker's watchdog would, a moment later
    return result
setattr(owner, name, wrapper)
from vtgen import cli
sys.exit(cli.main(sys.argv[3:]))
"""

IMAGE_WRITE, TABLE_WRITE, RENAME = "PIL.Image:Image.save", "pandas:DataFrame.to_parquet", "pathlib:Path.rename"
TILE_WRITE = "vtgen.stages.roi:write_tile_png"  # the roi stage writes its tiles with OpenCV's encoder
KILLS = {
    # stage: (command, output folder, function, the call after which the process is killed)
    "render": ("render --params params.yaml --out data/raw/synthetic", "data/raw/synthetic", IMAGE_WRITE, 5),
    "ingest": ("ingest --params params.yaml --out data/ingest", "data/ingest", TABLE_WRITE, 2),
    "roi": ("roi --params params.yaml --manifest data/ingest/manifest.parquet --out data/roi", "data/roi", TILE_WRITE, 7),
    "pairs": ("pairs --params params.yaml --tiles data/roi/tiles.parquet --out data/pairs", "data/pairs", RENAME, 1),
    "train": ("train --params params.yaml --direction v2t --scope all --pairs data/pairs --out models/v2t/all",
              "models/v2t/all", RENAME, 1),
    "generate": ("generate --params params.yaml --direction v2t --pairs data/pairs --models models/v2t "
                 "--out data/generated/v2t", "data/generated/v2t", IMAGE_WRITE, 3),
}


@pytest.mark.parametrize("stage", list(KILLS))
def test_a_stage_killed_part_way_leaves_its_previous_output_or_none_and_reruns(dvc_project, stage, monkeypatch, tmp_path):
    project = dvc_project
    command, out, target, at = KILLS[stage]
    out_dir = project / out
    previous = snapshot(out_dir)
    if stage == "train":
        shutil.copy(out_dir / "generator.pt", tmp_path / "generator_before.pt")
    killed = subprocess.run([sys.executable, "-c", KILLER, target, str(at), *command.split()], cwd=project, env=ENV,
                            capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]

    tmp, old = out_dir.with_name(f".{out_dir.name}.tmp"), out_dir.with_name(f".{out_dir.name}.old")
    if target == RENAME:  # killed between moving the old output aside and moving the new one in: no output
        assert not out_dir.exists() and snapshot(old) == previous
    else:  # killed while writing: the previous output is untouched, the partial one is in the temporary folder
        assert snapshot(out_dir) == previous
        assert tmp.is_dir() and snapshot(tmp) != previous

    monkeypatch.chdir(project)
    assert cli.main(command.split()) == 0
    again = snapshot(out_dir)
    # the same data; timing.json aside (this run wrote one, and outputs restored by `dvc pull` hold none)
    assert stable(again) == stable(previous) and data_only(again).keys() == data_only(previous).keys()
    if stage == "train":
        assert same_weights(out_dir / "generator.pt", tmp_path / "generator_before.pt")
    assert not tmp.exists() and not old.exists()


# ---------------------------------------------------------------------------------------------
# Training killed for real by SIGKILL under Snakemake; the next `snakemake --cores 2` resumes it

def test_training_killed_mid_run_resumes_under_snakemake_to_the_same_weights(tmp_path):
    params = tiny_params()
    params["presets"]["fast"]["iterations"] = 120
    params["translation"]["checkpoint_every"] = 10
    # the default mode; patience 8 keeps it training to step 80 at least, so a loaded machine that is slow to
    # deliver the kill still catches it well before the end (with patience 3 it stopped at step 30)
    params["translation"]["capacity"].update(mode="auto", eval_every=10, patience=8)
    project = make_project(tmp_path / "project", params)
    run(["snakemake", "--cores", "2", "data/pairs"], project)
    # the reference: the same training, uninterrupted, with its own checkpoint folder
    run(["vtgen", "train", "--params", "params.yaml", "--direction", "v2t", "--scope", "all", "--pairs", "data/pairs",
         "--out", str(tmp_path / "reference"), "--checkpoints", str(tmp_path / "reference_checkpoints")], project)

    # capacity auto: width probes of 4 steps, then the chosen width goes on in its own checkpoint folder
    def continuing() -> Path | None:
        for path in (project / "checkpoints/v2t/all").glob("**/last.pt"):
            try:
                if torch.load(path, weights_only=False)["step"] > params["translation"]["capacity"]["probe_iterations"]:
                    return path
            except Exception:  # noqa: BLE001 - a checkpoint being replaced
                pass
        return None

    reference = json.loads((tmp_path / "reference/train.json").read_text())
    assert reference["steps"] > 10, "the reference run stopped too early to test a resume"
    snakemake = subprocess.Popen(["snakemake", "--cores", "2", "data/generated/v2t"], cwd=project, env=ENV,
                                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    import psutil

    deadline = time.monotonic() + 300
    while (checkpoint := continuing()) is None:
        if snakemake.poll() is not None or time.monotonic() > deadline:
            snakemake.kill()
            pytest.fail(f"no checkpoint appeared while Snakemake ran:\n{snakemake.communicate()[0][-3000:]}")
        time.sleep(0.02)
    trainers = [p for p in psutil.Process(snakemake.pid).children(recursive=True)
                if "train" in p.cmdline() and any(part.endswith("vtgen") for part in p.cmdline())]
    assert len(trainers) == 1, [p.cmdline() for p in psutil.Process(snakemake.pid).children(recursive=True)]
    os.kill(trainers[0].pid, signal.SIGKILL)
    log = snakemake.communicate(timeout=120)[0]
    assert snakemake.returncode != 0, log[-3000:]

    step = torch.load(checkpoint, weights_only=False)["step"]
    assert 0 < step < reference["steps"], f"killed at step {step}: too late to test a resume"
    assert not (project / "models/v2t/all").exists()  # no half-written model folder
    assert not (project / "data/generated/v2t").exists()

    rerun = run(["snakemake", "--cores", "2", "data/generated/v2t"], project)
    assert f"resuming from step {step}" in rerun.stdout + rerun.stderr
    summary = read_with_times(project / "models/v2t/all/train.json")  # the resumed step: in timing.json
    assert summary["resumed_from_step"] == step and summary["steps"] == reference["steps"]
    assert same_weights(project / "models/v2t/all/generator.pt", tmp_path / "reference/generator.pt")
    assert (project / "data/generated/v2t/generated.parquet").is_file()


# ---------------------------------------------------------------------------------------------
# A full disk and folders that cannot be written: one line that says what and where

def no_space(*args, **kwargs):
    """What a write raises on a full disk: errno 28 and no file name (checked against /dev/full:
    Pillow, pyarrow and plain file writes all raise it this way)."""
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize("stage, patch", [("ingest", "pandas.DataFrame.to_parquet"), ("roi", "PIL.Image.Image.save"),
                                          ("pairs", "pandas.DataFrame.to_parquet")])
def test_a_full_disk_stops_a_stage_with_one_line_naming_the_output(dvc_project, tmp_path, monkeypatch, capsys,
                                                                  stage, patch):
    monkeypatch.chdir(dvc_project)
    monkeypatch.setattr(patch, no_space)
    inputs = {"ingest": [], "roi": ["--manifest", "data/ingest/manifest.parquet"],
              "pairs": ["--tiles", "data/roi/tiles.parquet"]}[stage]
    out = tmp_path / "out"
    code, err = cli_error([stage, "--params", "params.yaml", *inputs, "--out", str(out)], capsys)
    assert code == 2 and "Traceback" not in err
    assert err.endswith("\n") and err.rstrip("\n").split("\n")[-1] == (  # above it: the progress bar, if any
        f"vtgen {stage}: error: no space left on device (disk full) while writing {out}; "
        f"free some space or write to another disk, then run again")
    assert not out.exists() and not (tmp_path / ".out.tmp").exists()  # the partial output is removed, freeing space


def test_a_full_disk_names_the_file_when_the_writer_knows_it(dvc_project, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(dvc_project)

    def full(self, path, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    monkeypatch.setattr("pandas.DataFrame.to_parquet", full)
    code, err = cli_error(["ingest", "--params", "params.yaml", "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and f"while writing {tmp_path / '.out.tmp' / 'manifest.parquet'};" in err


def test_a_full_disk_while_checkpointing_is_reported_as_a_full_disk(dvc_project, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(dvc_project)
    for width in ("width_4", "width_8"):  # capacity auto: one checkpoint folder per width of the tiny params
        checkpoints = tmp_path / "checkpoints" / "v2t" / "all" / width
        checkpoints.mkdir(parents=True)
        (checkpoints / "last.pt.tmp").symlink_to("/dev/full")  # a real ENOSPC from the kernel
    code, err = cli_error(["train", "--params", "params.yaml", "--direction", "v2t", "--scope", "all", "--pairs",
                           "data/pairs", "--out", str(tmp_path / "model"), "--checkpoints", str(tmp_path / "checkpoints")],
                          capsys)
    assert code == 2 and "no space left on device" in err


def test_an_output_under_a_file_or_onto_a_file_is_refused_before_any_work(dvc_project, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(dvc_project)
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder\n")
    code, err = cli_error(["ingest", "--params", "params.yaml", "--out", str(blocker / "sub" / "ingest")], capsys)
    assert (code, err) == (2, f"vtgen ingest: error: {blocker / 'sub' / 'ingest'}: cannot create the output folder: "
                              f"{blocker} is a file\n")
    code, err = cli_error(["pairs", "--params", "params.yaml", "--tiles", "data/roi/tiles.parquet", "--out",
                           str(blocker)], capsys)
    assert (code, err) == (2, f"vtgen pairs: error: {blocker}: exists and is a file, not an output folder\n")
    assert blocker.read_text() == "not a folder\n"


def test_an_unwritable_output_folder_is_refused_with_its_name(dvc_project, tmp_path):
    """Permission bits do not stop root, so as root the command runs with CAP_DAC_OVERRIDE dropped (setpriv)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    command = [sys.executable, "-m", "vtgen", "ingest", "--params", "params.yaml", "--out", str(locked / "ingest")]
    if os.geteuid() == 0:
        if not shutil.which("setpriv"):
            pytest.skip("running as root without setpriv: cannot take away root's permission override")
        drop = "-dac_override,-dac_read_search"
        command = ["setpriv", f"--inh-caps={drop}", f"--bounding-set={drop}", *command]
    result = subprocess.run(command, cwd=dvc_project, env=ENV, capture_output=True, text=True)
    locked.chmod(0o755)
    assert result.returncode == 2, result.stderr
    assert result.stderr == (f"vtgen ingest: error: {locked / 'ingest'}: cannot write the output folder: "
                             f"{locked} is not writable\n")
    assert "ingest:" not in result.stdout  # refused before decoding the dataset
    assert list(locked.iterdir()) == []


@pytest.mark.parametrize("error, expected", [
    (OSError(errno.EROFS, "Read-only file system", "/mnt/data/out"),
     "/mnt/data/out: read-only file system; write the outputs to a writable disk"),
    (OSError(errno.EDQUOT, "Disk quota exceeded"), "disk quota exceeded; free some space or write to another disk, "
                                                   "then run again"),
    (PermissionError(errno.EACCES, "Permission denied", "/srv/x"),
     "/srv/x: permission denied; check the folder's permissions or choose another location"),
    (OSError(errno.EIO, "Input/output error", b"/data/\xff.png"), "/data/\\xff.png: Input/output error"),
])
def test_os_errors_are_described_with_what_happened_and_where(error, expected):
    assert describe_os_error(error) == expected


def test_a_write_error_without_a_file_name_is_given_the_output_folder(tmp_path):
    with pytest.raises(OSError) as caught:
        with atomic_output_dir(tmp_path / "out"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert caught.value.filename == str(tmp_path / "out")
    with pytest.raises(OutputDirError, match="exists and is a file"):
        (tmp_path / "file").write_text("x")
        with atomic_output_dir(tmp_path / "file"):
            pass


# ---------------------------------------------------------------------------------------------
# The SLURM profile: what a dry run plans, with the executor plugin installed

def planned_jobs(text: str) -> list[dict]:
    """Jobs of a `snakemake -n` listing: rule, wildcards, threads, resources, input, local (run by Snakemake itself)."""
    jobs = []
    for line in text.splitlines():
        if match := re.match(r"^(local)?rule (\w+):$", line):
            jobs.append({"rule": match[2], "wildcards": {}, "threads": 1, "resources": {}, "input": [],
                         "local": bool(match[1])})
        elif jobs and (match := re.match(r"^    (\w+): (.*)$", line)):
            key, value = match.groups()
            if key == "wildcards":
                jobs[-1]["wildcards"] = dict(item.split("=", 1) for item in value.split(", "))
            elif key == "threads":
                jobs[-1]["threads"] = int(value)
            elif key == "resources":
                jobs[-1]["resources"] = dict(item.split("=", 1) for item in value.split(", "))
            elif key == "input":
                jobs[-1]["input"] = value.split(", ")
    return jobs


def test_slurm_profile_dry_run_plans_parallel_training_jobs(tmp_path):
    params = tiny_params()
    params["translation"]["scope"] = ["all", "denim", "felt"]
    project = make_project(tmp_path / "project", params)
    # --cores only lifts the dry run's default cap of 1 core per job (on the cluster there is none),
    # so that the listing shows the threads each job will ask SLURM for
    dry = run(["snakemake", "-n", "--workflow-profile", "workflow/profiles/slurm", "--cores", "64"], project)
    assert "workflow specific profile workflow/profiles/slurm" in dry.stderr
    jobs = planned_jobs(dry.stdout)
    by_rule: dict[str, list[dict]] = {}
    for job in jobs:
        by_rule.setdefault(job["rule"], []).append(job)
    assert {rule: len(j) for rule, j in by_rule.items()} == {
        "render": 1, "ingest": 1, "roi": 1, "pairs": 1, "settings": 2, "train": 6, "generate": 2, "score": 1, "classify": 2,
        "report": 1, "all": 1}

    training = by_rule["train"]
    assert {(j["wildcards"]["direction"], j["wildcards"]["scope"]) for j in training} == {
        (d, s) for d in ("v2t", "t2v") for s in ("all", "denim", "felt")}
    for job in training:
        assert job["threads"] == params["translation"]["threads"]
        assert not any(i.startswith("models/") for i in job["input"])  # no training job waits for another
    for job in by_rule["generate"]:
        assert {i for i in job["input"] if i.startswith("models/")} == {
            f"models/{job['wildcards']['direction']}/{s}" for s in ("all", "denim", "felt")}
    # memory and time as the profile asks for a first attempt (its expressions of Snakemake's `attempt`); no GPU
    profile = yaml.safe_load((REPO / "workflow/profiles/slurm/config.yaml").read_text())["set-resources"]
    threads = {"render": 2, "ingest": 2, "roi": 2, "train": params["translation"]["threads"]}
    for rule, jobs_of_rule in by_rule.items():
        for job in jobs_of_rule if rule not in ("all", "settings") else []:  # local rules: no SLURM job
            asked = tuple(str(eval(str(profile[rule][key]), {"attempt": 1})) for key in ("mem_mb", "runtime"))
            assert (job["resources"]["mem_mb"], job["resources"]["runtime"], job["threads"]) == \
                (*asked, threads.get(rule, 1)), rule
            assert "gpu" not in job["resources"]

    # what sbatch would be given for a training job, by the plugin's own functions
    from snakemake_executor_plugin_slurm.submit_string import get_submit_command
    from snakemake_executor_plugin_slurm.utils import set_gres_string

    class Resources(dict):
        __getattr__ = dict.get

    job = SimpleNamespace(threads=2, resources=Resources(gpu=1, mem_mb=64000, runtime=720))
    call = get_submit_command(job, {"run_uuid": "u", "slurm_logfile": "log", "comment_str": "train", "account": "",
                                    "partition": "", "workdir": str(project)}) + set_gres_string(job)
    assert "--mem 64000" in call and "-t 720" in call and "--gpus=1" in call and "--cpus-per-task=2" in call


def test_default_profile_runs_locally_on_two_cores():
    profile = yaml.safe_load((REPO / "workflow/profiles/default/config.yaml").read_text())
    assert profile["cores"] == 2 and "executor" not in profile
    slurm = yaml.safe_load((REPO / "workflow/profiles/slurm/config.yaml").read_text())
    assert slurm["executor"] == "slurm" and "gpu" not in slurm["set-resources"]["train"]  # CPU torch: GPU lines are the site's


def test_plain_snakemake_applies_the_default_profile(tmp_path):
    project = make_project(tmp_path / "project", tiny_params())
    dry = run(["snakemake", "-n", "data/pairs"], project)
    assert "workflow specific profile profiles/default" in dry.stderr
    assert (project / "profiles/default").resolve() == (project / "workflow/profiles/default").resolve()


def test_a_disk_filling_up_mid_checkpoint_is_reported_as_a_full_disk_and_the_partial_file_removed(tmp_path, monkeypatch):
    """torch's zip writer reports a short write as RuntimeError ("unexpected pos ..."), seen when /tmp filled up
    during a main job; with the filesystem (nearly) full that is a full disk, else the error names the file."""
    from collections import namedtuple

    from vtgen.io import checkpoints

    def short_write(obj, handle):
        handle.write(b"x" * 1000)
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 90459392 vs 90459280")

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(checkpoints.torch, "save", short_write)
    target = tmp_path / "last.pt"
    monkeypatch.setattr(checkpoints.shutil, "disk_usage", lambda path: usage(10**9, 10**9 - 4096, 4096))
    with pytest.raises(OSError) as full:
        checkpoints.save_atomic({"step": 1}, target)
    assert full.value.errno == errno.ENOSPC and full.value.filename == str(tmp_path / "last.pt.tmp")
    assert not (tmp_path / "last.pt.tmp").exists() and not target.exists()
    monkeypatch.setattr(checkpoints.shutil, "disk_usage", lambda path: usage(10**12, 10**9, 10**11))
    with pytest.raises(RuntimeError, match=f"^{tmp_path / 'last.pt.tmp'}: .*unexpected pos"):
        checkpoints.save_atomic({"step": 1}, target)
    assert not (tmp_path / "last.pt.tmp").exists()
