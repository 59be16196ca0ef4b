# Translation stages: train (one job per direction and translation.scope entry) -> generate (per direction).
# Training jobs take translation.threads cores each, so `--cores 2` runs them one after another
# on a laptop and a cluster profile runs them side by side.
# Both read the tile images the pair tables list, so they declare data/roi as well as data/pairs.

from vtgen.config import DIRECTIONS

SCOPES = config["translation"]["scope"]
PRESET = config["presets"][config["translation"]["preset"]]


rule train:
    """Train the conditional GAN of one direction for one scope entry ('all' or a class)."""
    input:
        "data/pairs",
        "data/roi",
        "src/vtgen/train.py",
        "src/vtgen/gan.py",
        "src/vtgen/models.py",
    output:
        directory("models/{direction}/{scope}"),
    params:
        translation=config["translation"],
        preset=PRESET,
    threads: config["translation"]["threads"]
    wildcard_constraints:
        direction="|".join(DIRECTIONS),
        scope="[^/]+",
    benchmark:
        "logs/benchmarks/train_{direction}_{scope}.tsv"
    shell:
        "vtgen train --params params.yaml --direction {wildcards.direction} --scope {wildcards.scope} "
        "--pairs data/pairs --out models/{wildcards.direction}/{wildcards.scope}"


rule generate:
    """Translate the test split and generate.train_share of the training inputs of one direction."""
    input:
        "data/pairs",
        "data/roi",
        expand("models/{{direction}}/{scope}", scope=SCOPES),
        "src/vtgen/generate.py",
    output:
        directory("data/generated/{direction}"),
    params:
        generate=config["generate"],
        scope=SCOPES,
        device=config["translation"]["device"],
    wildcard_constraints:
        direction="|".join(DIRECTIONS),
    benchmark:
        "logs/benchmarks/generate_{direction}.tsv"
    shell:
        "vtgen generate --params params.yaml --direction {wildcards.direction} --pairs data/pairs "
        "--models models/{wildcards.direction} --out data/generated/{wildcards.direction}"
