# vtgen workflow. Run from the project root: `snakemake --cores 2` (or `make run`).
# The rules are built from the stage table in src/vtgen/pipeline.py, the same table `vtgen workflow`
# writes dvc.yaml from, so both tools run the same commands on the same inputs and outputs.
# Each rule's code inputs are the files its stage module imports; params.yaml is the one configuration.

import os
import sys

import yaml
from vtgen.io.params import validate_params
from vtgen.pipeline import commit_to_dvc, outputs, reconcile, snakemake_rule, stages, stale_dvc_yaml, write_params_records
from vtgen.io.runlock import hold_run_lock, run_holder

configfile: "params.yaml"

# Stage commands read params.yaml themselves, so overrides given only to Snakemake
# (--config, extra --configfile) would be silently ignored: refuse them instead.
if config != yaml.safe_load(open("params.yaml")):
    raise WorkflowError(
        "vtgen reads its configuration from params.yaml only; edit params.yaml "
        "(or use `dvc exp run -S key=value`) instead of --config/--configfile overrides"
    )
validate_params(config)
# each stage's params values as a file among its inputs: a changed value reruns the stage even when
# its outputs were made by DVC, of which Snakemake's own records know nothing
write_params_records(config)
# Snakemake decides by file times; vtgen's content records decide by content, as DVC does: a damaged output or
# an input whose content changed (below dataset.path too) reruns its job, and outputs whose content matches
# what made them (after `dvc pull`) are reused. Not in a cluster job, nor while another run holds the lock:
# then say so, since a "Nothing to be done" would otherwise read as "the outputs are sound".
if workflow.is_main_process:
    _holder = run_holder()
    if _holder:
        print(f"vtgen: another run of this project is in progress ({_holder}): outputs are not checked for damage "
              f"or changed inputs while it runs, and this run starts no job; run again when it has finished",
              file=sys.stderr)
    else:
        for _line in reconcile(config):
            print(_line, file=sys.stderr)
    # said now, not only at the end: a dvc.yaml written for other params (another dataset.source) is not recorded
    _stale = stale_dvc_yaml(config) if os.path.isdir(".dvc") else None
    if _stale:
        print(_stale, file=sys.stderr)

report: "workflow/report/workflow.rst"


# The default target is every output of the main job, not only the report: Snakemake does not rebuild a
# deleted intermediate output while the outputs after it exist, unless it is a target itself.
rule all:
    default_target: True
    input:
        outputs(config, "main"),


rule studies:
    """Every study (`snakemake studies`): trade-off, frontier, experiments, stability and their report."""
    input:
        outputs(config, "studies"),


for _stage in stages(config, "main") + stages(config, "studies"):
    _spec = snakemake_rule(_stage, config)

    rule:
        name: _stage.name
        input: _spec["input"]
        output: [directory(p) if p in _spec["directories"] else p for p in _spec["outputs"]]
        params: command=_spec["command"], **_spec["params"]
        threads: _spec["threads"]
        localrule: _spec["local"]
        wildcard_constraints: **_spec["constraints"]
        shell: "{params.command}"


# One run at a time per project, Snakemake or DVC: the lock is the kernel's (flock), so a killed run
# leaves nothing to unlock. Stage commands started by this run inherit the right to run.
onstart:
    hold_run_lock("snakemake")


# Record the finished stages in DVC too (`dvc commit` of those whose outputs match their content records), so
# that `dvc status` and `dvc repro` agree with this run instead of redoing it; only inside a DVC project.
onsuccess:
    _line = commit_to_dvc(config)
    if _line:
        print(_line, file=sys.stderr)
