"""The tiny main job on a real SLURM cluster, and its artefacts through a shared DVC remote over SSH.

The cluster and sshd are real daemons started by tests/cluster.py (skipped, with the reason, where the Debian
packages are missing or do not start). One SLURM run of the tiny job checks, together: every job in the
accounting records with the resources the profile asks, outputs byte-identical to the same job run locally
(the session's ``snakemake_project``), a training job cancelled mid-way (scancel) that the retry resumes from its
checkpoint, and a slurmd restart while a job runs.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from cluster import ACCOUNT, PARTITION, Unavailable, end_job_leftovers, start_slurm, start_sshd
from conftest import ENV, REPO, make_project, tiny_params
from vtgen.pipeline import STAGES

# The site settings of this cluster, given as a user gives them: account and partition for every job on the
# command line (docs/scaling.md); the profile's per-rule memory and time stay as committed.
SITE = ["--default-resources", f"slurm_account={ACCOUNT}", f"slurm_partition={PARTITION}"]
# a one-node cluster answers at once: poll job states every 2 s from the start instead of after 40 s
FAST_POLL = ["--slurm-init-seconds-before-status-checks", "2", "--slurm-keep-successful-logs"]


def test_timing_records_peak_memory_of_the_stage_and_its_workers():
    """peak_memory() reads the kernel's high-water marks: 1000 MB held by the process, 400 MB by a child it waited
    for. Importing vtgen.cli alone peaks at 300-740 MB here (torch; the load changes it), measured in a process
    that allocates nothing: the process's peak lies between 1000 MB and that plus 1000 MB."""
    start = "import numpy as np, subprocess, sys; from vtgen.cli import peak_memory;"
    # the child first: a child forked after the parent's allocation counts the parent's pages until it execs
    allocate = ("subprocess.run([sys.executable, '-c', 'import numpy as np; b = np.ones(400 * 2**20, np.uint8)'], check=True);"
                "a = np.ones(1000 * 2**20, np.uint8);")
    baseline, peaks = (eval(subprocess.run([sys.executable, "-c", start + middle + "print(peak_memory())"],
                                           capture_output=True, text=True, check=True).stdout)  # the dict printed
                       for middle in ("", allocate))
    assert 1000 <= peaks["peak_rss_mb"] < baseline["peak_rss_mb"] + 1000 + 100
    assert 400 <= peaks["peak_rss_children_mb"] < 500 and baseline["peak_rss_children_mb"] < 400


def test_requests_scale_measured_peaks_by_the_data(tmp_path):
    """measured_requests.py: the largest peak per rule from a run's timing.json files, then the documented formula."""
    spec = importlib.util.spec_from_file_location("requests_py", REPO / "workflow/profiles/slurm/measured_requests.py")
    requests = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(requests)
    for folder, record in {"data/roi": ("roi", 100, 400, 250), "models/v2t/all": ("train", 600, 900, 0),
                           "models/t2v/all": ("train", 500, 700, 0), "old": ("pairs", 5, None, None)}.items():
        (tmp_path / folder).mkdir(parents=True)
        stage, seconds, peak, child = record
        timing = {"stage": stage, "seconds": seconds} | ({"peak_rss_mb": peak, "peak_rss_children_mb": child}
                                                         if peak is not None else {})
        (tmp_path / folder / "timing.json").write_text(json.dumps(timing))
    peaks = requests.measured(tmp_path)
    assert peaks == {"roi": {"seconds": 100, "peak_rss_mb": 400, "peak_rss_children_mb": 250},
                     "train": {"seconds": 600, "peak_rss_mb": 900, "peak_rss_children_mb": 0}}  # no peak: left out
    params = {"ingest": {"workers": 2}}
    assert requests.requests(peaks, params) == {"roi": {"mem_mb": 2200, "runtime": 10},  # 2 x (400 + 2 x 250) + 400
                                                "train": {"mem_mb": 2200, "runtime": 20}}
    assert requests.requests(peaks, params, data=10, train=3) == {"roi": {"mem_mb": 18400, "runtime": 35},
                                                                  "train": {"mem_mb": 5800, "runtime": 60}}


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    try:
        cluster = start_slurm(tmp_path_factory.mktemp("slurm"))
    except Unavailable as exc:
        pytest.skip(f"no test SLURM cluster here: {exc}")
    try:
        yield cluster
    finally:
        cluster.stop()


LOCAL_RULES = {stage.name for stage in STAGES if stage.local}


def planned_jobs(project: Path, env: dict) -> dict[str, dict]:
    """Every job of a dry run with the SLURM profile: {"rule_<name>[_wildcards_<values>]": its resources}, the
    names being the comment the SLURM plugin gives each job."""
    # --cores only lifts the dry run's cap of 1 core per job, so that it lists the CPUs each job asks SLURM for
    dry = subprocess.run(["snakemake", "-n", "--workflow-profile", "workflow/profiles/slurm", *SITE, "--cores", "64"],
                         cwd=project, env=env, capture_output=True, text=True)
    assert dry.returncode == 0, dry.stdout[-3000:] + dry.stderr[-3000:]
    jobs = {}
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", dry.stdout):
        head = re.match(r"(?:local)?rule (\w+):", block)
        if not head or head[1] == "all" or head[1] in LOCAL_RULES:  # run by Snakemake itself: no SLURM job
            continue
        wildcards = re.search(r"^\s+wildcards: (.*)$", block, flags=re.M)
        name = f"rule_{head[1]}" + ("_wildcards_" + "_".join(w.split("=", 1)[1] for w in wildcards[1].split(", "))
                                    if wildcards else "")
        resources = dict(item.split("=", 1) for item in re.search(r"^\s+resources: (.*)$", block, re.M)[1].split(", "))
        threads = re.search(r"^\s+threads: (\d+)$", block, flags=re.M)
        jobs[name] = {"mem_mb": int(resources["mem_mb"]), "runtime": int(resources["runtime"]),
                      "cpus": int(threads[1]) if threads else 1}
    return jobs


class Disturbances(threading.Thread):
    """While the workflow runs: scancel the t2v training job once it has written a checkpoint, then restart slurmd
    while the resubmitted job runs. Records what it did in ``done``."""

    def __init__(self, slurm, project: Path, workflow: subprocess.Popen):
        super().__init__(daemon=True)
        self.slurm, self.project, self.workflow, self.done, self.error = slurm, project, workflow, {}, None

    def running(self, comment: str) -> list[str]:
        queue = self.slurm.command("squeue", "--noheader", "--format=%i|%k|%T", check=False).stdout
        return [line.split("|")[0] for line in queue.splitlines()
                if line.split("|")[1:] == [comment, "RUNNING"]]

    def run(self):
        try:
            target = "rule_train_wildcards_t2v_all"
            while self.workflow.poll() is None and "scancel" not in self.done:
                jobs = self.running(target)
                if jobs and list((self.project / "checkpoints/t2v/all").rglob("last.pt")):
                    self.slurm.command("scancel", jobs[0])
                    self.done["scancel"] = jobs[0]
                time.sleep(0.2)
            while self.workflow.poll() is None and "slurmd_restart" not in self.done:
                retried = [j for j in self.running(target) if j != self.done["scancel"]]
                if retried:
                    self.slurm.restart_slurmd()
                    self.done["slurmd_restart"] = retried[0]
                time.sleep(0.2)
        except Exception as exc:  # noqa: BLE001 - reported by the test
            self.error = exc


@pytest.mark.e2e
def test_tiny_main_job_through_slurm_matches_the_local_run_and_heals(slurm, snakemake_project, tmp_path):
    local, local_run = snakemake_project
    local_log = local_run.stdout + local_run.stderr
    project = make_project(tmp_path / "project", tiny_params())
    env = {k: v for k, v in ENV.items() if not k.startswith(("SLURM_", "SBATCH_", "SALLOC_", "SRUN_"))}
    env["SLURM_CONF"] = slurm.env["SLURM_CONF"]  # the test cluster, not a SLURM job pytest may itself run in
    planned = planned_jobs(project, env)
    assert len(planned) == 12 and all(job["mem_mb"] <= slurm.memory_mb for job in planned.values()), planned

    log = open(tmp_path / "snakemake.log", "w")
    workflow = subprocess.Popen(["snakemake", "--workflow-profile", "workflow/profiles/slurm", *SITE, *FAST_POLL],
                                cwd=project, env=env, stdout=log, stderr=subprocess.STDOUT)
    disturb = Disturbances(slurm, project, workflow)
    disturb.start()
    try:
        code = workflow.wait(timeout=1500)
    finally:
        if workflow.poll() is None:
            workflow.send_signal(signal.SIGINT)  # Snakemake cancels its SLURM jobs
            workflow.wait(60)
        log.close()
        leftovers = end_job_leftovers(project)
    text = (tmp_path / "snakemake.log").read_text()
    print(f"\nprocesses of ended jobs still running after the workflow, killed: {leftovers or 'none'}")
    assert code == 0, text[-4000:]
    disturb.join(10)
    assert disturb.error is None, disturb.error
    assert set(disturb.done) == {"scancel", "slurmd_restart"}, disturb.done

    # every rule instance is a job in the accounting records, with the resources the profile asks
    run_uuid = re.search(r"SLURM run ID: ([0-9a-f-]+)", text)[1]
    records = slurm.jobs(run_uuid)
    jobs = [j for j in records if "." not in j["JobIDRaw"]]  # allocations, not their steps
    print(f"\nthe tiny job: {wall_seconds(local_log)} s locally, {wall_seconds(text)} s through SLURM in {len(jobs)} jobs")
    steps = {j["JobIDRaw"]: j["MaxRSS"] for j in records if "." in j["JobIDRaw"]}
    for job in jobs:
        print(f"  {job['JobIDRaw']:>3} {job['Comment']:32} {job['State']:15} {job['Elapsed']} {job['ReqCPUS']} CPUs "
              f"{job['ReqMem']:>6} {job['Timelimit']}  MaxRSS batch {steps.get(job['JobIDRaw'] + '.batch', '-')}, "
              f"step {steps.get(job['JobIDRaw'] + '.0', '-')}")
    completed = {j["Comment"]: j for j in jobs if j["State"] == "COMPLETED"}
    assert set(completed) == set(planned)
    for name, want in planned.items():
        job = completed[name]
        attempt = 2 if name == "rule_train_wildcards_t2v_all" else 1  # the retry asks twice the memory and time
        assert (job["Account"], job["Partition"]) == (ACCOUNT, PARTITION)
        assert job["ReqMem"] == f"{want['mem_mb'] * attempt}M", name
        assert job["ReqCPUS"] == str(want["cpus"]), name
        assert job["Timelimit"] == time.strftime("%H:%M:%S", time.gmtime(want["runtime"] * attempt * 60)), name
    cancelled = [j for j in jobs if j["JobIDRaw"] == disturb.done["scancel"]]
    assert len(cancelled) == 1 and cancelled[0]["State"].startswith("CANCELLED")
    assert len(jobs) == len(planned) + 1  # the cancelled training job and its retry

    # the retry resumed from the checkpoint the cancelled job wrote
    retry_log = project / f".snakemake/slurm_logs/rule_train/t2v_all/{completed['rule_train_wildcards_t2v_all']['JobIDRaw']}.log"
    assert "resuming from step" in retry_log.read_text()

    # the same final weights, and byte-identical images and metrics, as the same job run locally
    for direction in ("v2t", "t2v"):
        mine, theirs = (weights(root / f"models/{direction}/all/generator.pt") for root in (project, local))
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine), direction
    assert images(project) == images(local) and len(images(local)) > 10
    assert (project / "reports/metrics.json").read_bytes() == (local / "reports/metrics.json").read_bytes()


def wall_seconds(log: str) -> int:
    """Seconds between the first and the last job timestamp of a Snakemake log."""
    stamps = [time.mktime(time.strptime(t, "%a %b %d %H:%M:%S %Y")) for t in re.findall(r"^\[(\w{3} \w{3} +\d+ [\d:]+ \d{4})\]$", log, re.M)]
    return int(max(stamps) - min(stamps)) if stamps else -1


def weights(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)["state_dict"]


def images(root: Path) -> dict[str, str]:
    """SHA-256 of every generated image (and preview) under ``root``."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((root / "data/generated").rglob("*.png"))}


# ---------------------------------------------------------------------------------------------
# A shared DVC remote over SSH

@pytest.fixture
def sshd(tmp_path):
    try:
        daemons, port, key = start_sshd(tmp_path / "sshd")
    except Unavailable as exc:
        pytest.skip(f"no local sshd here: {exc}")
    try:
        yield daemons, port, key
    finally:
        daemons.stop()


def git_dvc_project(source: Path, where: Path, env: dict) -> Path:
    """A git repository of the finished tiny project with its outputs recorded in dvc.lock (not yet pushed)."""
    project = where / "origin"
    shutil.copytree(source, project, symlinks=True, ignore=shutil.ignore_patterns("locks", "incomplete", "__pycache__"))
    shutil.copy(REPO / ".gitignore", project / ".gitignore")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t"]
    for command in (["git", "init", "-q"], ["dvc", "init", "-q"], ["dvc", "config", "core.analytics", "false"],
                    ["dvc", "commit", "-f", "--with-deps", "report"], ["git", "add", "-A"],
                    git + ["commit", "-qm", "finished run"]):
        subprocess.run(command, cwd=project, env=env, check=True, capture_output=True)
    return project


def dvc(args: list[str], cwd: Path, env: dict, check: bool = True) -> subprocess.CompletedProcess:
    result = subprocess.run(["dvc", *args], cwd=cwd, env=env, capture_output=True, text=True)
    assert not check or result.returncode == 0, f"dvc {' '.join(args)}:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}"
    return result


def remote_files(remote: Path) -> tuple[dict[str, Path], list[Path]]:
    """(the objects of a DVC remote by name, the hidden files beside them: DVC uploads to ``.<random>.tmp`` and
    renames when complete)."""
    files = [p for p in (remote / "files/md5").rglob("*") if p.is_file()] if (remote / "files/md5").is_dir() else []
    objects = {"".join(p.relative_to(remote / "files/md5").parts): p for p in files if not p.name.startswith(".")}
    return objects, [p for p in files if p.name.startswith(".")]


def assert_whole(objects: dict[str, Path]) -> None:
    """Nothing half-written: every object's content matches the MD5 it is named by."""
    for name, path in objects.items():
        assert hashlib.md5(path.read_bytes()).hexdigest() == name.removesuffix(".dir"), path


def partial_upload(remote: Path) -> bool:
    """True while a file is being written on the remote (a non-empty upload under its temporary name)."""
    try:
        return any(p.stat().st_size > 0 for p in remote_files(remote)[1])
    except OSError:  # renamed meanwhile
        return False


def drop_connections(daemons) -> int:
    """Kill the per-connection processes of the test's sshd (its children): every open session drops at once."""
    parent, killed = daemons.processes["sshd"].pid, 0
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # the process ended meanwhile
        if int(fields[1]) == parent:  # field 4 of /proc/PID/stat: the parent's id
            os.kill(int(stat.parent.name), signal.SIGKILL)
            killed += 1
    return killed


@pytest.mark.e2e
def test_dvc_remote_over_ssh_round_trips_and_heals_a_dropped_push(snakemake_project, sshd, tmp_path):
    daemons, port, key = sshd
    home = tmp_path / "home"  # the user's known_hosts holds the server's key: host keys are checked, as in real use
    (home / ".ssh").mkdir(parents=True)
    host_key = (daemons.root / "host_ed25519.pub").read_text().split()
    (home / ".ssh/known_hosts").write_text(f"[127.0.0.1]:{port} {host_key[0]} {host_key[1]}\n")
    env = {**ENV, "HOME": str(home)}
    local, _ = snakemake_project
    origin = git_dvc_project(local, tmp_path, env)
    remote = tmp_path / "shared-remote"
    dvc(["remote", "add", "-d", "shared", f"ssh://root@127.0.0.1:{port}{remote}"], origin, env)
    dvc(["remote", "modify", "--local", "shared", "keyfile", str(key)], origin, env)  # the key stays out of git
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "shared remote"],
                   cwd=origin, env=env, check=True)

    # a push whose connection drops in the middle of a file: a large artefact makes the moment easy to catch
    (origin / "large.bin").write_bytes(np.random.default_rng(0).bytes(48 * 2**20))
    dvc(["add", "large.bin"], origin, env)
    subprocess.run(["git", "add", "-A"], cwd=origin, env=env, check=True)
    subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "a large artefact"],
                   cwd=origin, env=env, check=True)
    push = subprocess.Popen(["dvc", "push", "-j", "1"], cwd=origin, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    dropped = 0
    while push.poll() is None and not dropped:
        if partial_upload(remote):
            dropped = drop_connections(daemons)
        time.sleep(0.002)
    output = push.communicate(timeout=120)[0]
    assert dropped and push.returncode != 0, f"the push finished before its connection could be dropped:\n{output}"
    partial, _ = remote_files(remote)
    assert_whole(partial)  # the file cut short is not under its object's name (DVC uploads to a temporary name)

    dvc(["push"], origin, env)  # the same command again completes the upload
    objects, _ = remote_files(remote)
    assert len(objects) > len(partial)
    assert_whole(objects)
    assert "in sync" in dvc(["status", "--cloud"], origin, env).stdout.lower()

    # a colleague's fresh clone pulls everything and finds the pipeline up to date, with the same metrics
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(origin), str(clone)], env=env, check=True)
    dvc(["remote", "modify", "--local", "shared", "keyfile", str(key)], clone, env)
    dvc(["pull"], clone, env)
    assert "up to date" in dvc(["status", "dvc.yaml"], clone, env).stdout.lower()
    assert (clone / "reports/metrics.json").read_bytes() == (local / "reports/metrics.json").read_bytes()
    assert images(clone) == images(origin) and len(images(origin)) > 10
    assert (clone / "large.bin").read_bytes() == (origin / "large.bin").read_bytes()
