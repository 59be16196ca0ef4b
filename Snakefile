# vtgen workflow. Run from the project root: `snakemake --cores 2` (or `make run`).
# The rules are built from the stage table in src/vtgen/pipeline.py, the same table `vtgen workflow`
# writes dvc.yaml from, so both tools run the same commands on the same inputs and outputs.
# Each rule's code inputs are the files its stage module imports; params.yaml is the one configuration.

import yaml
from vtgen.io.params import validate_params
from vtgen.pipeline import snakemake_rule, stages
from vtgen.runlock import hold_run_lock

configfile: "params.yaml"

# Stage commands read params.yaml themselves, so overrides given only to Snakemake
# (--config, extra --configfile) would be silently ignored: refuse them instead.
if config != yaml.safe_load(open("params.yaml")):
    raise WorkflowError(
        "vtgen reads its configuration from params.yaml only; edit params.yaml "
        "(or use `dvc exp run -S key=value`) instead of --config/--configfile overrides"
    )
validate_params(config)

report: "workflow/report/workflow.rst"


rule all:
    default_target: True
    input:
        "reports/index.html",


rule studies:
    """Every study (`snakemake studies`): trade-off, frontier, experiments, stability and their report."""
    input:
        "reports/studies/index.html",


for _stage in stages(config, "main") + stages(config, "studies"):
    _spec = snakemake_rule(_stage, config)

    rule:
        name: _stage.name
        message: _stage.doc
        input: _spec["inputs"]
        output: [directory(p) if p in _spec["directories"] else p for p in _spec["outputs"]]
        params: **_spec["params"]
        threads: _spec["threads"]
        wildcard_constraints: **_spec["constraints"]
        shell: _spec["command"]


# One run at a time per project, Snakemake or DVC: the lock is the kernel's (flock), so a killed run
# leaves nothing to unlock. Stage commands started by this run inherit the right to run.
onstart:
    hold_run_lock("snakemake")
