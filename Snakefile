# vtgen workflow. Run from the project root: `snakemake --cores 2` (or `make run`).
# Every rule runs the same `vtgen <stage>` command as the matching DVC stage in dvc.yaml;
# rules hold no logic. params.yaml is the one configuration for both tools.

import yaml
from vtgen.config import validate_params

configfile: "params.yaml"

# Stage commands read params.yaml themselves, so overrides given only to Snakemake
# (--config, extra --configfile) would be silently ignored: refuse them instead.
if config != yaml.safe_load(open("params.yaml")):
    raise WorkflowError(
        "vtgen reads its configuration from params.yaml only; edit params.yaml "
        "(or use `dvc exp run -S key=value`) instead of --config/--configfile overrides"
    )
validate_params(config)


include: "workflow/rules/data.smk"
include: "workflow/rules/translation.smk"
include: "workflow/rules/evaluation.smk"
include: "workflow/rules/studies.smk"


report: "workflow/report/workflow.rst"


rule all:
    default_target: True
    input:
        "reports/index.html",
