"""Changing one parameter reruns exactly the stages that read it, and everything downstream of them.

A copy of the finished tiny project (the session's ``snakemake_project``) is recorded in DVC with
``dvc commit`` (what ``dvc repro`` would have written), so both tools start from the same finished
run. Then one value of params.yaml is changed at a time and each tool is asked what it would do:

* ``snakemake -n`` (default target): the jobs it would run; those whose reason is a parameter
  change are the stages that read the value, the others run because their inputs will change;
* ``dvc status`` of the default pipeline (``report`` and its upstream stages): the stages whose
  declared parameters changed (DVC names only those; ``dvc repro`` then reruns what follows).

Stage names follow DVC (``train@v2t-all``, ``classify@visual``); Snakemake jobs are named the same
way from their wildcards. Rules and stages outside the default target (studies) are not asked.
"""

from __future__ import annotations

import copy
import json
import re
import shutil
import subprocess

import networkx as nx
import pytest
import yaml

from conftest import ENV, REPO, run

pytestmark = pytest.mark.e2e

SETTINGS = {"settings@v2t", "settings@t2v"}
TRAIN = {"train@v2t-all", "train@t2v-all"}
GENERATE = {"generate@v2t", "generate@t2v"}
CLASSIFY = {"classify@visual", "classify@tactile"}
FROM_GENERATE = GENERATE | {"score"} | CLASSIFY | {"report", "all"}
FROM_TRAIN = TRAIN | FROM_GENERATE
FROM_PAIRS = {"pairs"} | SETTINGS | FROM_TRAIN  # the settings stage reads the pairs summary (recipe auto)
EVERYTHING = {"render", "ingest", "roi"} | FROM_PAIRS

# dotted key, new value, stages `dvc status` reports (the ones reading the key), jobs `snakemake -n` runs
CASES = [
    ("classify.epochs", 3, CLASSIFY, CLASSIFY | {"score", "report", "all"}),  # score reads classify's encoder
    ("score.batch_size", 64, {"score"}, {"score", "report", "all"}),
    ("generate.train_share", 0.25, GENERATE, FROM_GENERATE),
    ("translation.log_every", 3, SETTINGS | {"report"}, SETTINGS | FROM_TRAIN),
    ("translation.device", "cpu", SETTINGS | GENERATE | CLASSIFY | {"report"}, SETTINGS | FROM_TRAIN),
    ("presets.fast.iterations", 12, SETTINGS, SETTINGS | FROM_TRAIN),
    ("presets.paper.ngf", 16, set(), set()),  # a preset that translation.preset does not select
    ("pairing.seed", 1, {"pairs"}, FROM_PAIRS),
    ("roi.size", 24, {"roi"} | SETTINGS, {"roi"} | SETTINGS | FROM_PAIRS),  # a model records its ROI rule
    ("synthetic.seed", 1, {"render"}, EVERYTHING),
]


@pytest.fixture(scope="module")
def finished(snakemake_project, tmp_path_factory):
    """A copy of the finished tiny project, recorded by DVC too, and its params."""
    source, _ = snakemake_project
    project = tmp_path_factory.mktemp("rerun") / "project"
    # copy2 keeps modification times, and .snakemake/ holds the recorded params: still finished
    shutil.copytree(source, project, symlinks=True, ignore=shutil.ignore_patterns("locks", "incomplete"))
    # the repository's .gitignore ignores the outputs, so DVC writes no .gitignore files among them
    # (one in models/v2t/ would change generate's dependency models/v2t)
    shutil.copy(REPO / ".gitignore", project / ".gitignore")
    run(["git", "init", "-q"], project)
    run(["dvc", "init", "-q"], project)
    run(["dvc", "config", "core.analytics", "false"], project)
    run(["dvc", "commit", "-f", "--with-deps", "report"], project)
    params = yaml.safe_load((project / "params.yaml").read_text())
    assert "Nothing to be done" in run(["snakemake", "-n"], project).stdout
    assert dvc_changed(project) == set()
    return project, params


def dvc_changed(project) -> set[str]:
    return set(json.loads(run(["dvc", "status", "--json", "report", "--with-deps"], project).stdout))


def snakemake_jobs(dry_run: str) -> tuple[set[str], set[str]]:
    """(all jobs, jobs run because their params changed) of a `snakemake -n` output."""
    jobs, by_params = set(), set()
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", dry_run):
        head = re.match(r"(?:local)?rule (\w+):", block)
        if not head:
            continue
        wildcards = re.search(r"^\s+wildcards: (.*)$", block, flags=re.M)
        name = head[1] + ("@" + "-".join(w.split("=", 1)[1] for w in wildcards[1].split(", ")) if wildcards else "")
        jobs.add(name)
        # Snakemake's own params record, or vtgen's (a file among the inputs, see vtgen.pipeline.write_params_records)
        if re.search(r"^\s+reason:.*(Params have changed|Updated input files:.*\.vtgen/params/)", block, flags=re.M):
            by_params.add(name)
    return jobs, by_params


def with_value(params: dict, key: str, value) -> dict:
    edited = copy.deepcopy(params)
    *path, last = key.split(".")
    section = edited
    for part in path:
        section = section[part]
    assert last in section and section[last] != value, key
    section[last] = value
    return edited


@pytest.mark.parametrize("key, value, dvc_expected, snakemake_expected", CASES, ids=[c[0] for c in CASES])
def test_one_parameter_reruns_exactly_the_stages_that_depend_on_it(finished, key, value, dvc_expected, snakemake_expected):
    project, params = finished
    (project / "params.yaml").write_text(yaml.safe_dump(with_value(params, key, value), sort_keys=False))
    try:
        # the two tools only read; ask both at once
        smk = subprocess.Popen(["snakemake", "-n"], cwd=project, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                               text=True)
        changed = dvc_changed(project)
        dry_run = smk.communicate()[0]
        assert smk.returncode == 0, dry_run[-3000:]
    finally:
        (project / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
    jobs, by_params = snakemake_jobs(dry_run)

    assert changed == dvc_expected, f"dvc status after changing {key}"
    assert jobs == snakemake_expected, f"snakemake -n after changing {key}"
    if not snakemake_expected:
        assert "Nothing to be done" in dry_run
    # both tools agree: Snakemake runs the stages DVC names and everything after them in DVC's graph,
    # and gives changed params as the reason for those of them that no other changed stage precedes
    # (it gives one reason per job, "input files updated" once an upstream job reruns)
    from dvc.repo import Repo

    with Repo(str(project)) as repo:
        graph = repo.index.graph  # edges run from a stage to the stages it depends on
        stages = {stage.name: stage for stage in graph.nodes}
        main = {"report"} | {s.name for s in nx.descendants(graph, stages["report"])}  # the default target's stages
        after = {name: {s.name for s in nx.ancestors(graph, stages[name])} & main for name in dvc_expected}
    assert jobs - {"all"} == set(dvc_expected).union(*after.values())
    first = {name for name in dvc_expected if not any(name in after[other] for other in dvc_expected)}
    assert first <= by_params <= set(dvc_expected)


def test_after_restoring_the_parameters_nothing_is_left_to_do(finished):
    project, _ = finished
    assert "Nothing to be done" in run(["snakemake", "-n"], project).stdout
    assert dvc_changed(project) == set()


def test_a_stage_run_again_that_writes_the_same_data_leaves_the_stages_after_it_alone(finished, tmp_path):
    """Times are not data: ingest run again (by either tool) writes a new timing.json but the same data, so neither
    DVC nor Snakemake then finds a stage after it to run again. Before, the seconds in ingest's summary.json made
    the ROI stage and everything after it run again, training included."""
    source, _ = finished
    project = tmp_path / "project"
    shutil.copytree(source, project, symlinks=True)
    timing = project / "data/ingest/timing.json"
    before = timing.read_text()
    assert "Running stage 'ingest'" in run(["dvc", "repro", "-f", "-s", "ingest"], project).stdout
    assert timing.read_text() != before  # it ran
    assert dvc_changed(project) == set()
    before = timing.read_text()
    run(["snakemake", "--cores", "1", "--force", "data/ingest"], project)
    assert timing.read_text() != before  # it ran
    assert "Nothing to be done" in run(["snakemake", "-n"], project).stdout
    assert dvc_changed(project) == set()


def test_one_direction_s_value_retrains_that_direction_only_in_both_tools(finished, tmp_path):
    """A per-direction value ({v2t: x, t2v: y}) changed for T2V: Snakemake plans T2V's settings and training only,
    and after them only the visual classifier (tactile images come from V2T); DVC reruns both settings jobs (it
    reads whole sections), finds V2T's file unchanged and skips V2T's training and the tactile classifier."""
    source, params = finished
    project = tmp_path / "project"
    shutil.copytree(source, project, symlinks=True)
    run(["git", "add", "-A"], project)  # dvclive logs training into a repository with a first commit
    run(["git", "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "finished run"], project)
    edited = copy.deepcopy(params)
    edited["translation"]["conditioning"]["t2v"] = "none"
    assert params["translation"]["conditioning"]["t2v"] != "none"
    (project / "params.yaml").write_text(yaml.safe_dump(edited, sort_keys=False))
    v2t_model = (project / "models/v2t/all/generator.pt").read_bytes()

    jobs, by_params = snakemake_jobs(run(["snakemake", "-n"], project).stdout)
    assert jobs == {"settings@t2v", "train@t2v-all"} | FROM_GENERATE - {"generate@v2t", "classify@tactile"}
    assert by_params == {"settings@t2v"}

    reproduced = run(["dvc", "repro", "report"], project).stdout
    ran = set(re.findall(r"Running stage '([^']+)'", reproduced))
    assert {"settings@v2t", "settings@t2v", "train@t2v-all"} <= ran, reproduced[-3000:]
    assert not {"train@v2t-all", "generate@v2t", "classify@tactile"} & ran, reproduced[-3000:]
    assert "classify@visual" in ran, reproduced[-3000:]
    assert (project / "models/v2t/all/generator.pt").read_bytes() == v2t_model
    assert json.loads((project / "models/t2v/all/train.json").read_text())["conditioning"] == "none"
    assert dvc_changed(project) == set()
