"""Benchmark: how long `snakemake -n` and `dvc status` take on a finished run, and where the time goes.

Target: each answers in under 3 s on a finished run.

By default the project (``--project``, the repository) is copied into a scratch folder with its
outputs (data/, models/, reports/, logs/, .snakemake/ metadata; checkpoints/ and the DVC cache
are left out) and measured there, so nothing in the project changes:

* if Snakemake finds work to do (the code or parameters changed since the run), the copy is
  marked finished with ``snakemake --touch``, and the reasons are printed;
* if DVC has no record of the run (no dvc.lock: the run was made by Snakemake), it is recorded in
  the copy with ``dvc commit -f`` (which copies the outputs into the copy's DVC cache). DVC's
  state database (file hashes by inode, size and mtime) goes into the scratch folder, so runs
  with a warm and with a cold state can both be timed.

``--in-place`` times the project as it is instead (read-only commands; ``dvc status`` updates
DVC's own state database as usual) and reports what the commands say.

Each command runs ``--repeats`` times (default 5); the table gives the median wall-clock time
and the median CPU time (user + system of the child process), which other programs sharing the
cores disturb less. Rows below the two targets split the time into the tools' own start-up
(imports), reading the workflow (Snakefile / dvc.yaml with its parameters) and checking the
outputs.

    python benchmarks/workflow_overhead.py
    python benchmarks/workflow_overhead.py --in-place --repeats 3
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BIN = str(Path(sys.executable).parent)
ENV = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "DVC_NO_ANALYTICS": "1"}
WORKFLOW_FILES = ["Snakefile", "dvc.yaml", "dvc.lock", "params.yaml", ".dvcignore", ".gitignore"]
WORKFLOW_DIRS = ["workflow", "src"]
OUTPUT_DIRS = ["data", "models", "reports", "logs", ".snakemake"]
TARGET_S = 3.0


def run(cmd: list[str], cwd: Path, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True)
    if check and done.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed in {cwd}:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")
    return done


def timed(cmd: list[str], cwd: Path, repeats: int, before=None) -> tuple[float, float, str]:
    """Median wall and CPU seconds of ``cmd`` over ``repeats`` runs, and the last run's output."""
    walls, cpus, out = [], [], ""
    for _ in range(repeats):
        if before:
            before()
        usage = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run(cmd, cwd=cwd, env=ENV, capture_output=True, text=True)
        walls.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - usage.ru_utime + after.ru_stime - usage.ru_stime)
        out = done.stdout + done.stderr
        if done.returncode != 0:
            sys.exit(f"{' '.join(cmd)} failed:\n{out[-2000:]}")
    return statistics.median(walls), statistics.median(cpus), out


def copy_project(project: Path, where: Path) -> Path:
    where.mkdir(parents=True)
    for name in WORKFLOW_FILES:
        if (project / name).is_file():
            shutil.copy2(project / name, where / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.egg-info", "locks", "incomplete")
    for name in WORKFLOW_DIRS + OUTPUT_DIRS:
        if (project / name).is_dir():
            shutil.copytree(project / name, where / name, symlinks=True, ignore=ignore)  # copy2 keeps mtimes
    if (project / "profiles").is_symlink():
        os.symlink(os.readlink(project / "profiles"), where / "profiles")
    return where


def pending_jobs(dry_run: str) -> tuple[int, list[str]]:
    """Number of jobs and the distinct reasons in a `snakemake -n` output."""
    if "Nothing to be done" in dry_run:
        return 0, []
    reasons = sorted({line.strip() for line in dry_run.splitlines() if line.strip().startswith("reason:")
                      and "by another job" not in line})  # the root causes, not their consequences
    jobs = next((int(line.split()[-1]) for line in dry_run.splitlines() if line.startswith("total")), -1)
    return jobs, reasons


def finish_copy(project: Path, copy: Path, site_cache: Path) -> list[str]:
    """Make the copy a finished run for both tools; return notes on what had to be done."""
    notes = []
    run(["git", "init", "-q"], copy)
    run(["dvc", "init", "-q"], copy)
    if (project / ".dvc" / "config").is_file():  # the project's DVC settings, not its cache
        shutil.copy2(project / ".dvc" / "config", copy / ".dvc" / "config")
    run(["dvc", "config", "--local", "core.site_cache_dir", str(site_cache)], copy)
    run(["git", "add", "-A"], copy)
    run(["git", "-c", "user.name=bench", "-c", "user.email=bench@localhost", "commit", "-qm", "copy"], copy)

    jobs, reasons = pending_jobs(run(["snakemake", "-n"], copy).stdout)
    if jobs:
        notes.append(f"Snakemake had {jobs} job(s) to run in the project ({'; '.join(reasons[:4])}"
                     f"{' ...' if len(reasons) > 4 else ''}); the copy was marked finished with `snakemake --touch`")
        run(["snakemake", "--touch", "--cores", "1", "--quiet"], copy)
        jobs, reasons = pending_jobs(run(["snakemake", "-n"], copy).stdout)
        if jobs:
            notes.append(f"after --touch Snakemake still has {jobs} job(s): {'; '.join(reasons)}")
    had_lock = (copy / "dvc.lock").is_file()
    status = run(["dvc", "status"], copy).stdout
    if "up to date" not in status:
        notes.append("DVC " + ("found changes since dvc.lock" if had_lock else "had no dvc.lock (the run was made by Snakemake)")
                     + "; the copy recorded the run with `dvc commit -f report --with-deps`")
        run(["dvc", "commit", "-f", "--with-deps", "report"], copy)
    return notes


def dvc_params_parse_cost(project: Path) -> tuple[int, float]:
    """(stages that read params.yaml, CPU seconds DVC's YAML parser takes for params.yaml once)."""
    from dvc.repo import Repo
    from dvc.utils.serialize import parse_yaml

    with Repo(str(project)) as repo:
        stages = sum(1 for stage in repo.index.stages if any(d.def_path == "params.yaml" for d in stage.deps))
    text = (project / "params.yaml").read_text()
    start = time.process_time()
    for _ in range(10):
        parse_yaml(text, "params.yaml")
    return stages, (time.process_time() - start) / 10


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--project", type=Path, default=REPO)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--in-place", action="store_true", help="time the project as it is, without a copy")
    parser.add_argument("--keep", action="store_true", help="keep the scratch copy and print its path")
    args = parser.parse_args()
    project = args.project.resolve()
    scratch = Path(tempfile.mkdtemp(prefix="vtgen-overhead-"))
    site_cache = scratch / "dvc-site-cache"
    try:
        notes = []
        if args.in_place:
            where = project
        else:
            started = time.perf_counter()
            where = copy_project(project, scratch / "project")
            notes.append(f"measured in a copy of {project} ({time.perf_counter() - started:.0f} s to copy)")
            notes += finish_copy(project, where, site_cache)
        rows = []
        smk_wall, smk_cpu, smk_out = timed(["snakemake", "-n"], where, args.repeats)
        jobs, _ = pending_jobs(smk_out)
        rows.append(("`snakemake -n`", smk_wall, smk_cpu, "nothing to be done" if jobs == 0 else f"{jobs} jobs to run", True))
        dvc_wall, dvc_cpu, dvc_out = timed(["dvc", "status"], where, args.repeats)
        verdict = "up to date" if "up to date" in dvc_out else (
            f"{sum(1 for line in dvc_out.splitlines() if line.endswith(':') and not line.startswith(chr(9)))} stages changed")
        rows.append(("`dvc status`", dvc_wall, dvc_cpu, verdict, True))
        studies = sorted(str(p.relative_to(where)) for p in where.rglob("dvc.yaml") if p != where / "dvc.yaml"
                         and not any(part.startswith(".") for part in p.relative_to(where).parts))
        if studies:  # `dvc status` checks every dvc.yaml in the repository; time the main one alone too
            main_only = timed(["dvc", "status", "dvc.yaml"], where, args.repeats)
            rows.append(("`dvc status dvc.yaml` (the main pipeline only, without " + ", ".join(studies) + ")",
                         main_only[0], main_only[1], "up to date" if "up to date" in main_only[2] else "changes", False))
        if not args.in_place:
            cold = timed(["dvc", "status"], where, args.repeats, before=lambda: shutil.rmtree(site_cache, ignore_errors=True))
            rows.append(("`dvc status`, cold state db (every file re-hashed)", cold[0], cold[1], "", False))
        python = [sys.executable, "-c"]
        rows.append(("Snakemake start-up: `import snakemake.cli`", *timed(python + ["import snakemake.cli"], where, args.repeats)[:2],
                     "", False))
        rows.append(("`snakemake --list-rules` (start-up + Snakefile, no DAG)", *timed(["snakemake", "-l"], where, args.repeats)[:2],
                     "", False))
        rows.append(("DVC start-up: `import dvc.cli, dvc.repo`", *timed(python + ["import dvc.cli, dvc.repo"], where, args.repeats)[:2],
                     "", False))
        rows.append(("`dvc stage list` (start-up + dvc.yaml, no hashing)", *timed(["dvc", "stage", "list"], where, args.repeats)[:2],
                     "", False))
        stages, parse_s = dvc_params_parse_cost(where)

        print(f"Workflow overhead on a finished run; median of {args.repeats} runs; {os.cpu_count()} cores; "
              f"load average {os.getloadavg()[0]:.1f} at the end")
        for note in notes:
            print(f"- {note}")
        print()
        print("| command | wall s | CPU s | says | under 3 s |")
        print("|---|---:|---:|---|---|")
        for name, wall, cpu, says, target in rows:
            mark = ("yes" if wall < TARGET_S else "NO") if target else ""
            print(f"| {name} | {wall:.2f} | {cpu:.2f} | {says} | {mark} |")
        print()
        print(f"DVC reads params.yaml once per stage that lists params: {stages} stages x {1e3 * parse_s:.1f} ms "
              f"(ruamel.yaml, {len((where / 'params.yaml').read_text()):,} bytes) = {stages * parse_s:.2f} s CPU of each `dvc status`.")
    finally:
        if args.keep:
            print(f"scratch copy kept at {scratch}")
        else:
            shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
