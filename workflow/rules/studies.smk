# Study stages, outside the main job (`snakemake studies`): the speed-accuracy trade-off (one job
# per setting, all seeds inside), its frontier and capacity choice, the paper's experiment matrix
# (one job per run), the stability edge cases, and their report in reports/studies/.
# Experiments read the frontier because cloth_types trains each class at its capacity-auto setting.

TRADEOFF = list(config["studies"]["tradeoff"]["settings"])
EXPERIMENTS = list(config["studies"]["experiments"]["runs"])
# a study job uses the threads its base sets (translation.threads), else the main job's
STUDY_THREADS = {kind: config["studies"][kind]["base"].get("translation.threads", config["translation"]["threads"])
                 for kind in ("tradeoff", "experiments")}
STUDY_CODE = ["src/vtgen/studies.py", "src/vtgen/train.py", "src/vtgen/gan.py", "src/vtgen/models.py",
              "src/vtgen/generate.py", "src/vtgen/score.py", "src/vtgen/metrics.py", "src/vtgen/classifier.py"]


rule tradeoff_setting:
    """Train, generate and score one trade-off setting for every studies.tradeoff seed."""
    input:
        "data/pairs",
        "data/roi",
        STUDY_CODE,
    output:
        directory("data/studies/tradeoff/{setting}"),
    params:
        tradeoff=config["studies"]["tradeoff"],
        translation=config["translation"],
        preset=PRESET,
        classify=config["classify"],
    threads: STUDY_THREADS["tradeoff"]
    wildcard_constraints:
        setting="|".join(TRADEOFF),
    benchmark:
        "logs/benchmarks/tradeoff_{setting}.tsv"
    shell:
        "vtgen study --params params.yaml --kind tradeoff --name {wildcards.setting} --pairs data/pairs "
        "--out data/studies/tradeoff/{wildcards.setting}"


rule frontier:
    """Pareto frontier of the trade-off settings and the per-class capacity-auto choice."""
    input:
        expand("data/studies/tradeoff/{setting}", setting=TRADEOFF),
        "src/vtgen/studies.py",
    output:
        report(directory("data/studies/frontier"), patterns=["{name}.png"], caption="../report/studies.rst",
               category="Studies"),
    params:
        capacity=config["studies"]["capacity"],
    shell:
        "vtgen frontier --params params.yaml --runs data/studies/tradeoff --out data/studies/frontier"


rule experiment:
    """One row of the paper's experiment matrix (studies.experiments.runs)."""
    input:
        "data/pairs",
        "data/roi",
        "data/studies/frontier",
        STUDY_CODE,
    output:
        directory("data/studies/experiments/{name}"),
    params:
        experiments=config["studies"]["experiments"],
        translation=config["translation"],
        preset=PRESET,
        classify=config["classify"],
    threads: STUDY_THREADS["experiments"]
    wildcard_constraints:
        name="|".join(EXPERIMENTS),
    benchmark:
        "logs/benchmarks/experiment_{name}.tsv"
    shell:
        "vtgen study --params params.yaml --kind experiments --name {wildcards.name} --pairs data/pairs "
        "--capacity data/studies/frontier --out data/studies/experiments/{wildcards.name}"


rule stability:
    """Train at the edges of the parameter space; each case ends finite or with a clear message."""
    input:
        "src/vtgen/stability.py",
        "src/vtgen/train.py",
        "src/vtgen/models.py",
    output:
        directory("data/studies/stability"),
    params:
        translation=config["translation"],
        preset=PRESET,
    benchmark:
        "logs/benchmarks/stability.tsv"
    shell:
        "vtgen stability --params params.yaml --out data/studies/stability"


rule studies:
    """reports/studies/: the experiment rows beside the paper, the Pareto plot, capacity auto and stability."""
    input:
        expand("data/studies/experiments/{name}", name=EXPERIMENTS),
        "data/studies/frontier",
        "data/studies/stability",
        "src/vtgen/studies_report.py",
    output:
        "reports/studies/index.html",
        "reports/studies/summary.md",
        report(directory("reports/studies/figures"), patterns=["{name}.png"], caption="../report/studies.rst",
               category="Studies"),
    params:
        studies=config["studies"],
    shell:
        "vtgen studies-report --params params.yaml --experiments data/studies/experiments "
        "--frontier data/studies/frontier --stability data/studies/stability --out reports/studies"
