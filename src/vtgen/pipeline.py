"""The stage table: every stage of vtgen declared once.

Snakemake builds its rules from :data:`STAGES` in a loop (``Snakefile``) and ``vtgen workflow``
writes both DVC pipelines (``dvc.yaml`` for the main job, ``workflow/studies/dvc.yaml`` for the
studies) from it, so the two tools run the same commands on the same inputs and outputs.

A stage's code dependencies are never listed by hand: :func:`code_files` follows the imports of
the module that implements it, inside the ``vtgen`` package, so a change to any file the stage
runs reruns it and nothing else.

Paths may hold wildcards: ``{direction}`` (v2t, t2v), ``{modality}`` (visual, tactile),
``{scope}`` (translation.scope), ``{setting}`` (studies.tradeoff.settings) and ``{name}``
(studies.experiments.runs). A wildcard in a stage's outputs makes one job per value; one that
appears only in an input means "every value" (for ``{scope}``: the folder holding them all).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from vtgen.core.domain import DIRECTIONS, MODALITIES
from vtgen.io.params import SYNTHETIC_PATH
from vtgen.io.provenance import PACKAGE_ROOT, code_files

WILDCARD = re.compile(r"\{(\w+)\}")


@dataclass(frozen=True)
class Stage:
    """One pipeline stage. ``command`` is the shell command both tools run (wildcards as ``{name}``);
    ``params`` are dotted params.yaml keys (``presets.${translation.preset}`` resolves the preset);
    ``metrics`` and ``plots`` are small outputs versioned in git, not in the DVC cache; ``threads``
    is the params key that sets the job's cores; ``reads`` are non-Python files the code reads.
    Study stages keep their outputs out of the DVC cache: most projects never run them, and a
    never-run cached output would make every plain ``dvc pull`` and ``dvc exp apply`` fail."""

    name: str
    module: str
    command: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    params: tuple[str, ...] = ()
    metrics: tuple[str, ...] = ()
    plots: dict = field(default_factory=dict)
    threads: str | None = None
    reads: tuple[str, ...] = ()
    pipeline: str = "main"
    doc: str = ""

    def wildcards(self) -> list[str]:
        """Wildcards that make one job per value (those in the outputs), in order of appearance."""
        found = []
        for path in self.outputs:
            for name in WILDCARD.findall(path):
                if name not in found:
                    found.append(name)
        return found


STAGES: tuple[Stage, ...] = (
    Stage("render", "vtgen.stages.render", "vtgen render --params params.yaml --out data/raw/synthetic",
          inputs=(), outputs=(SYNTHETIC_PATH,), params=("synthetic",), threads="synthetic.workers",
          doc="Render the embedded SYNTHETIC ViTac-like dataset into the generic layout (only when dataset.source is synthetic)."),
    Stage("ingest", "vtgen.stages.ingest", "vtgen ingest --params params.yaml --out data/ingest",
          inputs=("${dataset.path}",), outputs=("data/ingest",), params=("dataset", "ingest"), threads="ingest.workers",
          doc="Read the dataset into manifest.parquet; bad files go to the quarantine table."),
    Stage("roi", "vtgen.stages.roi",
          "vtgen roi --params params.yaml --manifest data/ingest/manifest.parquet --out data/roi",
          inputs=("data/ingest", "${dataset.path}"), outputs=("data/roi",), params=("roi", "ingest.workers"),
          threads="ingest.workers",
          doc="Cut every image into tiles at roi.size (GelSight contact region for tactile frames)."),
    Stage("pairs", "vtgen.stages.pairs", "vtgen pairs --params params.yaml --tiles data/roi/tiles.parquet --out data/pairs",
          inputs=("data/roi",), outputs=("data/pairs",), params=("pairing",),
          doc="Assign train/val/test by source and write the V2T and T2V pair tables."),
    Stage("train", "vtgen.stages.train",
          "vtgen train --params params.yaml --direction {direction} --scope {scope} --pairs data/pairs "
          "--out models/{direction}/{scope}",
          inputs=("data/pairs", "data/roi"), outputs=("models/{direction}/{scope}",),
          params=("translation", "presets.${translation.preset}", "roi"), threads="translation.threads",
          doc="Train the conditional GAN of one direction for one scope entry ('all' or a class)."),
    Stage("generate", "vtgen.stages.generate",
          "vtgen generate --params params.yaml --direction {direction} --pairs data/pairs --models models/{direction} "
          "--out data/generated/{direction}",
          inputs=("data/pairs", "data/roi", "models/{direction}/{scope}"), outputs=("data/generated/{direction}",),
          params=("generate", "translation.scope", "translation.device"),
          doc="Translate the test split and generate.train_share of the training inputs of one direction."),
    Stage("score", "vtgen.stages.score",
          "vtgen score --params params.yaml --pairs data/pairs --generated data/generated --classify data/classify "
          "--out data/scores",
          inputs=("data/pairs", "data/roi", "data/generated/{direction}", "data/classify/{modality}"),
          outputs=("data/scores",), params=("score",),
          doc="Colour-SSIM (aligned, set-to-set, nearest real), KID, FID, spectrum, two-sample test, PRDC and "
              "memorisation, each beside reference levels."),
    Stage("classify", "vtgen.stages.classify",
          "vtgen classify --params params.yaml --modality {modality} --pairs data/pairs --generated data/generated "
          "--out data/classify/{modality}",
          inputs=("data/pairs", "data/roi", "data/generated/{direction}"), outputs=("data/classify/{modality}",),
          params=("classify", "translation.device"), threads="classify.threads",
          doc="AlexNet-style texture classifier of one modality: real only vs real + generated, over seeds."),
    Stage("report", "vtgen.stages.report",
          "vtgen report --params params.yaml --ingest data/ingest --pairs data/pairs --models models "
          "--generated data/generated --scores data/scores --classify data/classify --out reports",
          inputs=("data/ingest", "data/pairs", "models/{direction}/{scope}", "data/generated/{direction}", "data/scores",
                  "data/classify/{modality}"),
          outputs=("reports/index.html", "reports/summary.md", "reports/figures", "reports/timings.json"),
          metrics=("reports/metrics.json",),
          plots={"reports/plots/training.csv": {"x": "step", "y": "loss_g_l1", "title": "generator L1 loss by model"}},
          params=("dataset", "translation"), reads=("src/vtgen/io/templates",),
          doc="The run's report: reports/index.html, summary.md, metrics.json, plots and figures."),
    # studies: outside the main job (`snakemake studies`, `dvc repro workflow/studies/dvc.yaml`)
    Stage("tradeoff_setting", "vtgen.studies.study",
          "vtgen study --params params.yaml --kind tradeoff --name {setting} --pairs data/pairs "
          "--out data/studies/tradeoff/{setting}",
          inputs=("data/pairs", "data/roi"), outputs=("data/studies/tradeoff/{setting}",),
          params=("studies.tradeoff", "translation", "presets.${translation.preset}", "classify"),
          threads="translation.threads", pipeline="studies",
          doc="Train, generate and score one trade-off setting for every studies.tradeoff seed."),
    Stage("frontier", "vtgen.studies.study",
          "vtgen frontier --params params.yaml --runs data/studies/tradeoff --out data/studies/frontier",
          inputs=("data/studies/tradeoff/{setting}",), outputs=("data/studies/frontier",),
          params=("studies.capacity",), pipeline="studies",
          doc="Pareto frontier of the trade-off settings and the per-class capacity-auto choice."),
    Stage("experiment", "vtgen.studies.study",
          "vtgen study --params params.yaml --kind experiments --name {name} --pairs data/pairs "
          "--capacity data/studies/frontier --out data/studies/experiments/{name}",
          inputs=("data/pairs", "data/roi", "data/studies/frontier"), outputs=("data/studies/experiments/{name}",),
          params=("studies.experiments", "translation", "presets.${translation.preset}", "classify"),
          threads="translation.threads", pipeline="studies",
          doc="One row of the paper's experiment matrix (studies.experiments.runs)."),
    Stage("stability", "vtgen.studies.stability", "vtgen stability --params params.yaml --out data/studies/stability",
          inputs=(), outputs=("data/studies/stability",), params=("translation", "presets.${translation.preset}"),
          pipeline="studies",
          doc="Train at the edges of the parameter space; each case ends finite or with a clear message."),
    Stage("studies_report", "vtgen.studies.report",
          "vtgen studies-report --params params.yaml --experiments data/studies/experiments "
          "--frontier data/studies/frontier --stability data/studies/stability --out reports/studies",
          inputs=("data/studies/experiments/{name}", "data/studies/frontier", "data/studies/stability"),
          outputs=("reports/studies/index.html", "reports/studies/summary.md", "reports/studies/figures"),
          params=("studies",), reads=("src/vtgen/io/templates",), pipeline="studies",
          doc="reports/studies/: the experiment rows beside the paper, the Pareto plot, capacity auto and stability."),
)


def stages(params: dict, pipeline: str = "main") -> list[Stage]:
    """The stages of ``pipeline`` that apply to ``params`` (render only for the synthetic dataset)."""
    chosen = [s for s in STAGES if s.pipeline == pipeline]
    if params["dataset"]["source"] != "synthetic":
        chosen = [s for s in chosen if s.name != "render"]
    return chosen


# ----------------------------------------------------------------------------- code dependencies

def code_deps(stage: Stage, root: Path | None = None) -> list[str]:
    """``stage``'s code files as paths relative to the project root (``src/vtgen/...``), plus what it reads."""
    root = (root or PACKAGE_ROOT.parents[1]).resolve()
    files = [path.relative_to(root).as_posix() for path in code_files(stage.module)]
    return files + list(stage.reads)


# ----------------------------------------------------------------------------- wildcards and params

def wildcard_values(params: dict) -> dict[str, list[str]]:
    """The values each wildcard takes under ``params``."""
    studies = params["studies"]
    return {"direction": list(DIRECTIONS), "modality": list(MODALITIES), "scope": list(params["translation"]["scope"]),
            "setting": list(studies["tradeoff"]["settings"]), "name": list(studies["experiments"]["runs"])}


def resolve(text: str, params: dict) -> str:
    """Replace ``${dotted.key}`` with its value in ``params`` (DVC's interpolation, for Snakemake)."""
    def lookup(match: re.Match) -> str:
        node = params
        for part in match.group(1).split("."):
            node = node[part]
        return str(node)
    return re.sub(r"\$\{([\w.]+)\}", lookup, text)


def param_value(params: dict, key: str):
    node = params
    for part in resolve(key, params).split("."):
        node = node[part]
    return node


# ----------------------------------------------------------------------------- DVC

DVC_HEADER = {
    "main": "# The main job for DVC (`dvc repro`, `dvc exp run`), written by `vtgen workflow` from the stage table\n"
            "# in src/vtgen/pipeline.py: edit the table, not this file. Snakemake builds the same stages.\n",
    "studies": "# vtgen studies for DVC, outside the main job: `dvc repro workflow/studies/dvc.yaml`. Written by\n"
               "# `vtgen workflow` from the stage table in src/vtgen/pipeline.py: edit the table, not this file.\n",
}
DVC_FILES = {"main": Path("dvc.yaml"), "studies": Path("workflow/studies/dvc.yaml")}
# how DVC spells each wildcard's values: a fixed list, or an interpolation that follows params.yaml
DVC_VALUES = {"direction": list(DIRECTIONS), "modality": list(MODALITIES), "scope": "${translation.scope}",
              "setting": "${studies.tradeoff.settings}", "name": "${studies.experiments.runs}"}


def _dvc_path(path: str, own: list[str], item: dict[str, str]) -> list[str]:
    """One stage path in DVC terms: own wildcards become ``${item...}``; others expand (``{scope}``: its folder)."""
    names = WILDCARD.findall(path)
    others = [n for n in names if n not in own]
    for name in [n for n in others if isinstance(DVC_VALUES[n], str)]:  # values follow params: take their folder
        path = path.replace("/{" + name + "}", "")
        others.remove(name)
    for name in own:
        path = path.replace("{" + name + "}", item[name])
    paths = [path]
    for name in others:
        paths = [p.replace("{" + name + "}", value) for p in paths for value in DVC_VALUES[name]]
    return paths


def dvc_stage(stage: Stage, root: Path) -> dict:
    """``stage`` as a DVC stage definition (``foreach``/``matrix`` for one job per wildcard value)."""
    own = stage.wildcards()
    if len(own) == 1:  # foreach: ${key} over a mapping of params (settings, runs), ${item} over a list
        item = {own[0]: "${key}" if own[0] in ("setting", "name") else "${item}"}
    else:
        item = {name: "${item." + name + "}" for name in own}
    command = stage.command
    for name in own:
        command = command.replace("{" + name + "}", item[name])
    deps = [p for path in stage.inputs for p in _dvc_path(path, own, item)] + code_deps(stage, root)
    body: dict = {}
    if stage.pipeline != "main":
        body["wdir"] = "../.."
    body["cmd"] = command
    body["deps"] = deps
    if stage.params:
        body["params"] = list(stage.params)
    outs = [p for path in stage.outputs for p in _dvc_path(path, own, item)]
    body["outs"] = outs if stage.pipeline == "main" else [{path: {"cache": False}} for path in outs]
    if stage.metrics:
        body["metrics"] = [{path: {"cache": False}} for path in stage.metrics]
    if stage.plots:
        body["plots"] = [{path: {"cache": False, **spec}} for path, spec in stage.plots.items()]
    if not own:
        return body
    if len(own) == 1:
        return {"foreach": DVC_VALUES[own[0]], "do": body}
    return {"matrix": {name: DVC_VALUES[name] for name in own}, **body}


def dvc_yaml(params: dict, pipeline: str, root: Path | None = None) -> str:
    """The text of ``pipeline``'s dvc.yaml for ``params``."""
    root = root or PACKAGE_ROOT.parents[1]
    document: dict = {}
    if pipeline != "main":
        document["vars"] = ["../../params.yaml"]
    document["stages"] = {s.name: dvc_stage(s, root) for s in stages(params, pipeline)}
    return DVC_HEADER[pipeline] + yaml.dump(document, Dumper=_PlainDumper, sort_keys=False, width=120)


class _PlainDumper(yaml.SafeDumper):
    """YAML without anchors and aliases: DVC files a person can read."""

    def ignore_aliases(self, data) -> bool:
        return True


def write_dvc_files(params: dict, root: Path, check: bool = False) -> list[Path]:
    """Write (or with ``check``, only compare) both DVC files; return those that differ(ed) from the table."""
    changed = []
    for pipeline, relative in DVC_FILES.items():
        path = root / relative
        text = dvc_yaml(params, pipeline, root)
        if not path.is_file() or path.read_text() != text:
            changed.append(relative)
            if not check:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(text)
    return changed


# ----------------------------------------------------------------------------- Snakemake

def snakemake_rule(stage: Stage, params: dict, root: Path | None = None) -> dict:
    """What the Snakefile's rule loop needs: inputs (wildcards of other stages expanded), outputs,
    params values, threads and the shell command (a function of the job's wildcards)."""
    root = root or PACKAGE_ROOT.parents[1]
    own = stage.wildcards()
    values = wildcard_values(params)
    inputs = []
    for path in stage.inputs:
        paths = [resolve(path, params)]
        for name in WILDCARD.findall(path):
            if name not in own:
                paths = [p.replace("{" + name + "}", v) for p in paths for v in values[name]]
        inputs += paths
    outputs = list(stage.outputs) + list(stage.metrics) + list(stage.plots)
    return {
        "inputs": inputs + code_deps(stage, root) + [params_record(stage)],
        "outputs": outputs,
        "directories": [p for p in stage.outputs if not Path(p).suffix],
        "params": {key.replace(".", "_").replace("${", "").replace("}", ""): param_value(params, key)
                   for key in stage.params},
        "threads": param_value(params, stage.threads) if stage.threads else 1,
        "constraints": {name: "|".join(re.escape(v) for v in values[name]) for name in own},
        "command": _command_for(stage.command),
    }


PARAMS_RECORDS = Path(".vtgen") / "params"


def params_record(stage: Stage) -> str:
    """The file holding the params values ``stage`` reads, a Snakemake input (see :func:`write_params_records`)."""
    return (PARAMS_RECORDS / f"{stage.name}.json").as_posix()


def write_params_records(params: dict, root: Path = Path(".")) -> None:
    """Write each stage's params values to its record, touching only records whose values changed.

    Snakemake notices changed params through its own metadata, which outputs made by another tool
    (``dvc repro``) do not have: it would then call the outputs of a run on other data up to date.
    A record is an input like any file, so a changed value reruns the stage whoever made its outputs.
    """
    import json

    for stage in stages(params, "main") + stages(params, "studies"):
        path = root / params_record(stage)
        text = json.dumps({key: param_value(params, key) for key in stage.params}, sort_keys=True) + "\n"
        if not path.is_file() or path.read_text() != text:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)


def outputs(params: dict, pipeline: str = "main") -> list[str]:
    """Every output path of ``pipeline``'s jobs under ``params``. The Snakefile's default target asks for all
    of them, so a deleted intermediate output is rebuilt, and everything after it reruns."""
    values = wildcard_values(params)
    found = []
    for stage in stages(params, pipeline):
        for path in (*stage.outputs, *stage.metrics, *stage.plots):
            paths = [path]
            for name in WILDCARD.findall(path):
                paths = [p.replace("{" + name + "}", v) for p in paths for v in values[name]]
            found += paths
    return found


def _command_for(template: str):
    """The shell command of one job, as a Snakemake params function: the Snakefile's rule loop must not
    read its loop variables when a job runs (they hold the last stage by then)."""
    def command(wildcards) -> str:
        return template.format(**dict(wildcards.items()))
    return command
