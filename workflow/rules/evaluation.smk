# Evaluation stages: score (both directions) -> classify (one job per modality) -> report.
# Outputs marked with report() also appear in `snakemake --report report.html`.

MODALITIES = ["visual", "tactile"]


rule score:
    """Colour-SSIM (aligned, set-to-set, nearest real), grey SSIM, PSNR, MS-SSIM, with reference levels."""
    input:
        "data/pairs",
        "data/roi",
        expand("data/generated/{direction}", direction=list(DIRECTIONS)),
        "src/vtgen/score.py",
        "src/vtgen/metrics.py",
    output:
        report(directory("data/scores"), patterns=["{name}.csv"], caption="../report/scores.rst",
               category="Scores"),
    params:
        score=config["score"],
    benchmark:
        "logs/benchmarks/score.tsv"
    shell:
        "vtgen score --params params.yaml --pairs data/pairs --generated data/generated --out data/scores"


rule classify:
    """AlexNet-style texture classifier of one modality: real only vs real + generated, 3 seeds."""
    input:
        "data/pairs",
        "data/roi",
        expand("data/generated/{direction}", direction=list(DIRECTIONS)),
        "src/vtgen/classify.py",
        "src/vtgen/classifier.py",
    output:
        report(directory("data/classify/{modality}"), patterns=["{name}.png"], caption="../report/classify.rst",
               category="Classification", subcategory="{modality}"),
    params:
        classify=config["classify"],
        device=config["translation"]["device"],
    threads: config["classify"]["threads"]
    wildcard_constraints:
        modality="|".join(MODALITIES),
    benchmark:
        "logs/benchmarks/classify_{modality}.tsv"
    shell:
        "vtgen classify --params params.yaml --modality {wildcards.modality} --pairs data/pairs "
        "--generated data/generated --out data/classify/{wildcards.modality}"


rule report:
    """The run's report: reports/index.html, summary.md, metrics.json and figures/."""
    input:
        "data/ingest",
        "data/pairs",
        expand("models/{direction}/{scope}", direction=list(DIRECTIONS), scope=SCOPES),
        expand("data/generated/{direction}", direction=list(DIRECTIONS)),
        "data/scores",
        expand("data/classify/{modality}", modality=MODALITIES),
        "src/vtgen/report.py",
    output:
        "reports/index.html",
        "reports/summary.md",
        "reports/metrics.json",
        report(directory("reports/figures"), patterns=["{name}.png"], caption="../report/figures.rst",
               category="Report"),
    params:
        dataset=config["dataset"],
        translation=config["translation"],
    shell:
        "vtgen report --params params.yaml --out reports"
