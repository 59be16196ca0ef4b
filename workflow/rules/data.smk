# Data stages: render (synthetic only) -> ingest -> roi -> pairs.
# Each `params:` entry names the params.yaml values the stage reads, so changing one reruns the stage.
# The roi stage reads the images the manifest lists, so it declares the dataset folder too.


rule render:
    """Render the embedded SYNTHETIC ViTac-like dataset into the generic layout."""
    input:
        "src/vtgen/synthetic.py",
    output:
        directory("data/raw/synthetic"),
    params:
        synthetic=config["synthetic"],
    threads: config["synthetic"]["workers"]
    benchmark:
        "logs/benchmarks/render.tsv"
    shell:
        "vtgen render --params params.yaml --out data/raw/synthetic"


rule ingest:
    """Read the dataset into manifest.parquet; bad files go to the quarantine table."""
    input:
        config["dataset"]["path"],
        "src/vtgen/ingest.py",
        "src/vtgen/imageio.py",
    output:
        directory("data/ingest"),
    params:
        dataset=config["dataset"],
        ingest=config["ingest"],
    threads: config["ingest"]["workers"]
    benchmark:
        "logs/benchmarks/ingest.tsv"
    shell:
        "vtgen ingest --params params.yaml --out data/ingest"


rule roi:
    """Cut every image into tiles at roi.size (GelSight contact region for tactile frames)."""
    input:
        "data/ingest",
        config["dataset"]["path"],
        "src/vtgen/tiling.py",
        "src/vtgen/roi.py",
        "src/vtgen/imageio.py",
    output:
        directory("data/roi"),
    params:
        roi=config["roi"],
        workers=config["ingest"]["workers"],
    threads: config["ingest"]["workers"]
    benchmark:
        "logs/benchmarks/roi.tsv"
    shell:
        "vtgen roi --params params.yaml --manifest data/ingest/manifest.parquet --out data/roi"


rule pairs:
    """Assign train/val/test by source and write the V2T and T2V pair tables."""
    input:
        "data/roi",
        "src/vtgen/pairing.py",
    output:
        directory("data/pairs"),
    params:
        pairing=config["pairing"],
    benchmark:
        "logs/benchmarks/pairs.tsv"
    shell:
        "vtgen pairs --params params.yaml --tiles data/roi/tiles.parquet --out data/pairs"
