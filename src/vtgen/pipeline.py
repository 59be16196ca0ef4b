"""The stage table: every stage of vtgen declared once.

Snakemake builds its rules from :data:`STAGES` in a loop (``Snakefile``) and ``vtgen workflow``
writes the DVC pipelines from it (``dvc.yaml``, the main job, committed; ``workflow/studies/dvc.yaml``,
the studies, only on request: see :func:`write_dvc_files`), so the two tools run the same commands on
the same inputs and outputs.

A stage's code dependencies are never listed by hand: :func:`code_files` follows the imports of
the module that implements it, inside the ``vtgen`` package, so a change to any file the stage
runs reruns it and nothing else.

Paths may hold wildcards: ``{direction}`` (v2t, t2v), ``{modality}`` (visual, tactile),
``{scope}`` (translation.scope), ``{setting}`` (studies.tradeoff.settings) and ``{name}``
(studies.experiments.runs). A wildcard in a stage's outputs makes one job per value; one that
appears only in an input means "every value" (for ``{scope}``: the folder holding them all).
``{producer}`` in an input follows the job's ``{modality}``: the direction whose output it is (:data:`DERIVED`), so
a modality's classifier waits for its own generator only.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from vtgen.core.domain import DIRECTIONS, MODALITIES, direction_producing
from vtgen.io.params import SYNTHETIC_PATH, settings_record
from vtgen.io.provenance import PACKAGE_ROOT, code_files

WILDCARD = re.compile(r"\{(\w+)\}")


@dataclass(frozen=True)
class Stage:
    """One pipeline stage. ``command`` is the shell command both tools run (wildcards as ``{name}``);
    ``params`` are dotted params.yaml keys (``presets.${translation.preset}`` resolves the preset);
    ``metrics`` and ``plots`` are small outputs versioned in git, not in the DVC cache; ``threads``
    is the params key that sets the job's cores; ``reads`` are non-Python files the code reads.
    ``record_by`` (only ``direction``) makes the params record per job: it holds
    :func:`vtgen.io.params.settings_record` of the job's direction, not the whole sections, so Snakemake reruns
    only the job whose direction's values changed (DVC, reading the sections, reruns every job of the stage, whose
    unchanged outputs then rerun nothing after them). ``local``: a job of a second that Snakemake runs itself, never
    as a cluster job.
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
    record_by: str | None = None
    local: bool = False
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
    Stage("settings", "vtgen.stages.settings",
          "vtgen settings --params params.yaml --direction {direction} --pairs data/pairs --out data/settings/{direction}",
          # data/pairs: the data kind translation.recipe auto chooses from
          inputs=("data/pairs",), outputs=("data/settings/{direction}",),
          params=("translation", "presets.${translation.preset}", "recipes", "roi"), record_by="direction", local=True,
          doc="Write the params values one direction's training reads, per-direction values resolved (train depends on it)."),
    Stage("train", "vtgen.stages.train",
          "vtgen train --params params.yaml --direction {direction} --scope {scope} --pairs data/pairs "
          "--tiles data/roi/tiles.parquet --out models/{direction}/{scope}",
          # data/ingest: the md5s of the frames that class_gan.views crops again; data/settings: its params values
          inputs=("data/settings/{direction}", "data/pairs", "data/roi", "data/ingest"), outputs=("models/{direction}/{scope}",),
          threads="translation.threads",
          doc="Train the conditional GAN of one direction for one scope entry ('all' or a class)."),
    Stage("generate", "vtgen.stages.generate",
          "vtgen generate --params params.yaml --direction {direction} --pairs data/pairs --models models/{direction} "
          "--out data/generated/{direction}",
          inputs=("data/pairs", "data/roi", "models/{direction}/{scope}"), outputs=("data/generated/{direction}",),
          params=("generate", "translation.scope", "translation.device", "translation.recipe", "recipes"),
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
          inputs=("data/pairs", "data/roi", "data/generated/{producer}"), outputs=("data/classify/{modality}",),
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
          params=("dataset", "translation", "recipes"), reads=("src/vtgen/io/templates",),
          doc="The run's report: reports/index.html, summary.md, metrics.json, plots and figures."),
    # studies: outside the main job (`snakemake studies`; for DVC, `vtgen workflow --studies` first, then
    # `dvc repro workflow/studies/dvc.yaml`)
    Stage("tradeoff_setting", "vtgen.studies.study",
          "vtgen study --params params.yaml --kind tradeoff --name {setting} --pairs data/pairs "
          "--out data/studies/tradeoff/{setting}",
          inputs=("data/pairs", "data/roi"), outputs=("data/studies/tradeoff/{setting}",),
          params=("studies.tradeoff", "translation", "presets.${translation.preset}", "recipes", "classify"),
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
          params=("studies.experiments", "translation", "presets.${translation.preset}", "recipes", "classify"),
          threads="translation.threads", pipeline="studies",
          doc="One row of the paper's experiment matrix (studies.experiments.runs)."),
    Stage("stability", "vtgen.studies.stability", "vtgen stability --params params.yaml --out data/studies/stability",
          inputs=(), outputs=("data/studies/stability",), params=("translation", "presets.${translation.preset}", "recipes"),
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
    if not PACKAGE_ROOT.is_relative_to(root):  # PACKAGE_ROOT is resolved, and so is every code file under it
        raise ValueError(f"the vtgen that runs here is {PACKAGE_ROOT}, outside this project ({root}), so the workflow cannot "
                         f"name the code each stage depends on as paths inside the project: run it with this project's "
                         f"vtgen (`pip install -e .` here, or PYTHONPATH=src python -m vtgen ...)")
    files = [path.relative_to(root).as_posix() for path in code_files(stage.module)]
    return files + list(stage.reads)


# ----------------------------------------------------------------------------- wildcards and params

def wildcard_values(params: dict) -> dict[str, list[str]]:
    """The values each wildcard takes under ``params``."""
    studies = params["studies"]
    return {"direction": list(DIRECTIONS), "modality": list(MODALITIES), "scope": list(params["translation"]["scope"]),
            "setting": list(studies["tradeoff"]["settings"]), "name": list(studies["experiments"]["runs"])}


# placeholders computed from a job's own wildcard: name -> (that wildcard, its value -> this one's)
DERIVED = {"producer": ("modality", direction_producing)}


def with_derived(item: dict[str, str]) -> dict[str, str]:
    """A job's wildcard values plus the :data:`DERIVED` placeholders they determine."""
    return {**item, **{name: rule(item[source]) for name, (source, rule) in DERIVED.items() if source in item}}


def fill(path: str, item: dict[str, str]) -> str:
    """``path`` with each ``{name}`` of ``item`` replaced by its value."""
    for key, value in item.items():
        path = path.replace("{" + key + "}", value)
    return path


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
               "# `vtgen workflow --studies` from the stage table in src/vtgen/pipeline.py: edit the table, not this\n"
               "# file. Not committed: while it exists, plain `dvc status` lists the study stages too; delete this\n"
               "# folder (with its dvc.lock) to leave DVC with the main job alone.\n",
}
DVC_FILES = {"main": Path("dvc.yaml"), "studies": Path("workflow/studies/dvc.yaml")}
# how DVC spells each wildcard's values: a fixed list, or an interpolation that follows params.yaml
DVC_VALUES = {"direction": list(DIRECTIONS), "modality": list(MODALITIES), "scope": "${translation.scope}",
              "setting": "${studies.tradeoff.settings}", "name": "${studies.experiments.runs}"}


def _dvc_path(path: str, own: list[str], item: dict[str, str]) -> list[str]:
    """One stage path in DVC terms: own wildcards become ``${item...}``; others expand (``{scope}``: its folder)."""
    names = WILDCARD.findall(path)
    others = [n for n in names if n not in own and n not in DERIVED]
    for name in [n for n in others if isinstance(DVC_VALUES[n], str)]:  # values follow params: take their folder
        path = path.replace("/{" + name + "}", "")
        others.remove(name)
    paths = [fill(path, {name: item[name] for name in [*own, *(n for n in names if n in DERIVED)]})]
    for name in others:
        paths = [p.replace("{" + name + "}", value) for p in paths for value in DVC_VALUES[name]]
    return paths


def dvc_stage(stage: Stage, root: Path) -> dict:
    """``stage`` as a DVC stage definition (``foreach``/``matrix`` for one job per wildcard value)."""
    own = stage.wildcards()
    derived = sorted({n for path in stage.inputs for n in WILDCARD.findall(path) if n in DERIVED})
    if derived and own != [DERIVED[derived[0]][0]]:
        raise ValueError(f"stage {stage.name}: {{{derived[0]}}} needs the one wildcard {{{DERIVED[derived[0]][0]}}}")
    if derived:  # foreach over a mapping: ${key} is the value of the job's wildcard, ${item.<name>} what follows from it
        item = {own[0]: "${key}", **{name: "${item." + name + "}" for name in derived}}
    elif len(own) == 1:  # foreach: ${key} over a mapping of params (settings, runs), ${item} over a list
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
    # persist: DVC leaves the outputs in place until the command replaces them (atomically), so a `dvc repro`
    # that the run lock then refuses has removed nothing of the run that holds the lock
    cached = {} if stage.pipeline == "main" else {"cache": False}
    body["outs"] = [{path: {**cached, "persist": True}} for path in outs]
    if stage.metrics:
        body["metrics"] = [{path: {"cache": False, "persist": True}} for path in stage.metrics]
    if stage.plots:
        body["plots"] = [{path: {"cache": False, "persist": True, **spec}} for path, spec in stage.plots.items()]
    if not own:
        return body
    if derived:
        values = {value: {name: with_derived({own[0]: value})[name] for name in derived} for value in DVC_VALUES[own[0]]}
        return {"foreach": values, "do": body}
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


def write_dvc_files(params: dict, root: Path, check: bool = False, studies: bool = False) -> list[Path]:
    """Write (or with ``check``, only compare) the DVC files; return those that differ(ed) from the table.

    ``dvc.yaml`` always; the studies' file only with ``studies`` or when it already exists (kept current, never
    left stale). It is not committed, because DVC collects every dvc.yaml in the repository: a committed one
    makes plain ``dvc status`` list every never-run study stage. Nor can it be git-ignored: DVC refuses to
    run a git-ignored dvc.yaml or dvc.lock."""
    changed = []
    for pipeline, relative in DVC_FILES.items():
        path = root / relative
        if pipeline != "main" and not studies and not path.is_file():
            continue
        text = dvc_yaml(params, pipeline, root)
        if not path.is_file() or path.read_text() != text:
            changed.append(relative)
            if not check:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(text)
    return changed


# ----------------------------------------------------------------------------- Snakemake

def stage_threads(stage: Stage, params: dict) -> int:
    """The cores a job of ``stage`` declares: its ``threads`` parameter, else 1 (Snakemake's default)."""
    return int(param_value(params, stage.threads)) if stage.threads else 1


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
            if name not in own and name not in DERIVED:
                paths = [p.replace("{" + name + "}", v) for p in paths for v in values[name]]
        inputs += paths
    inputs += code_deps(stage, root) + [params_record(stage)]
    outputs = list(stage.outputs) + list(stage.metrics) + list(stage.plots)
    return {
        "inputs": inputs,
        # what the rule's input directive takes: the paths, or with a DERIVED placeholder a function of the wildcards
        "input": _inputs_for(inputs) if any(n in DERIVED for p in inputs for n in WILDCARD.findall(p)) else inputs,
        "outputs": outputs,
        "directories": [p for p in stage.outputs if not Path(p).suffix],
        # a per-job record (record_by) holds the values; the rule's own params would hold every direction's
        "params": {} if stage.record_by else {key.replace(".", "_").replace("${", "").replace("}", ""):
                                               param_value(params, key) for key in stage.params},
        "threads": stage_threads(stage, params),
        "local": stage.local,
        "constraints": {name: "|".join(re.escape(v) for v in values[name]) for name in own},
        "command": _command_for(stage.command),
    }


PARAMS_RECORDS = Path(".vtgen") / "params"


def params_record(stage: Stage, item: dict[str, str] | None = None) -> str:
    """The file holding the params values ``stage`` reads, a Snakemake input (see :func:`write_params_records`):
    one per stage, or with ``record_by`` one per value of that wildcard (given in ``item``, else left as the
    wildcard, as the Snakemake rule names it)."""
    if stage.record_by is None:
        return (PARAMS_RECORDS / f"{stage.name}.json").as_posix()
    value = (item or {}).get(stage.record_by, "{" + stage.record_by + "}")
    return (PARAMS_RECORDS / stage.name / f"{value}.json").as_posix()


def write_params_records(params: dict, root: Path = Path(".")) -> None:
    """Write each stage's params values to its record, touching only records whose values changed.

    Snakemake notices changed params through its own metadata, which outputs made by another tool
    (``dvc repro``) do not have: it would then call the outputs of a run on other data up to date.
    A record is an input like any file, so a changed value reruns the stage whoever made its outputs.
    """
    values = wildcard_values(params)
    for stage in stages(params, "main") + stages(params, "studies"):
        for item in ([{stage.record_by: v} for v in values[stage.record_by]] if stage.record_by else [None]):
            path = root / params_record(stage, item)
            text = params_text(stage, params, item)
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


def _inputs_for(paths: list[str]):
    """A Snakemake input function: ``paths`` with the job's wildcards and the DERIVED placeholders filled in."""
    def inputs(wildcards) -> list[str]:
        item = with_derived(dict(wildcards.items()))
        return [fill(path, item) for path in paths]
    return inputs


def _command_for(template: str):
    """The shell command of one job, as a Snakemake params function: the Snakefile's rule loop must not
    read its loop variables when a job runs (they hold the last stage by then)."""
    def command(wildcards) -> str:
        return template.format(**dict(wildcards.items()))
    return command


# ----------------------------------------------------------------------------- content records

@dataclass(frozen=True)
class Job:
    """One job of a stage: its DVC-style name (``train@v2t-all``), concrete inputs and outputs."""

    name: str
    stage: Stage
    wildcards: dict
    inputs: tuple[str, ...]   # data inputs, then code files
    outputs: tuple[str, ...]

    @property
    def record_dir(self) -> str:
        """Where the job's content record lives: its first folder output (``reports/figures`` for the report)."""
        return next(p for p in self.outputs if not Path(p).suffix)


def jobs(params: dict, pipeline: str = "main") -> list[Job]:
    """Every job of ``pipeline`` under ``params``, upstream before downstream."""
    import itertools

    values = wildcard_values(params)
    found = []
    for stage in stages(params, pipeline):
        own = stage.wildcards()
        for combination in itertools.product(*(values[name] for name in own)):
            item = dict(zip(own, combination))
            rule = snakemake_rule(stage, params)
            full = with_derived(item)
            name = stage.name + ("@" + "-".join(combination) if combination else "")
            found.append(Job(name, stage, item, tuple(fill(p, full) for p in rule["inputs"][:-1]),
                             tuple(fill(p, full) for p in rule["outputs"])))
    made_by = {out: job for job in found for out in job.outputs}
    ordered, done = [], set()

    def visit(job: Job) -> None:
        if job.name in done:
            return
        done.add(job.name)
        for path in job.inputs:
            upstream = made_by.get(path)
            if upstream is not None:
                visit(upstream)
        ordered.append(job)

    for job in found:
        visit(job)
    return ordered


def params_text(stage: Stage, params: dict, item: dict[str, str] | None = None) -> str:
    """The params values ``stage`` reads, as the text of its params record; with ``record_by``, those of the job
    whose wildcards are ``item`` (:func:`vtgen.io.params.settings_record`)."""
    import json

    if stage.record_by is not None:
        return json.dumps(settings_record(params, item[stage.record_by]), sort_keys=True) + "\n"
    return json.dumps({key: param_value(params, key) for key in stage.params}, sort_keys=True) + "\n"


def input_hashes(job: Job, params: dict, hasher) -> dict[str, str | None]:
    """Content hash of each input of ``job``, and of the params values it reads (key ``params``)."""
    import hashlib

    hashes = {path: hasher.hash(path) for path in job.inputs}
    hashes["params"] = hashlib.md5(params_text(job.stage, params, job.wildcards).encode()).hexdigest()
    return hashes


def job_of_command(params: dict, command: str, out: str) -> Job | None:
    """The main or studies job a stage command writing ``out`` runs, or None when ``out`` is not a declared output."""
    out = Path(out).as_posix().rstrip("/")
    for pipeline in ("main", "studies"):
        for job in jobs(params, pipeline):
            if job.stage.command.split()[1] == command and out in (job.outputs[0], Path(job.outputs[0]).parent.as_posix()):
                return job
    return None


def _snakemake_mtime(path: str) -> float | None:
    """The modification time Snakemake reads for ``path`` (a folder's ``.snakemake_timestamp`` when present)."""
    try:
        if os.path.isdir(path) and os.path.exists(os.path.join(path, ".snakemake_timestamp")):
            return os.stat(os.path.join(path, ".snakemake_timestamp")).st_mtime
        return os.stat(path).st_mtime
    except OSError:
        return None


def _set_mtime(paths, ns: int) -> None:
    for path in paths:
        for target in (os.path.join(path, ".snakemake_timestamp"), path):
            if os.path.exists(target):
                os.utime(target, ns=(ns, ns), follow_symlinks=True)


MISSING, UNRECORDED = "an output is missing", "no content record"
CHANGED = "input "
STALE_NS = 10**9  # 1970-01-01 00:00:01: older than any input (Snakemake reads a time of 0 as no time at all)


def job_problem(job: Job, params: dict, hasher) -> str | None:
    """None when ``job``'s outputs hold what it wrote and its inputs are what it read (by content); else why not:
    MISSING, UNRECORDED, or the first damaged output or changed input in words."""
    from vtgen.io.contents import damage, read_record

    if not all(os.path.exists(p) for p in job.outputs):
        return MISSING
    record = read_record(job.record_dir)
    if record is None:
        return UNRECORDED
    problem = damage(record, list(job.outputs), hasher)
    if problem is None:
        current = input_hashes(job, params, hasher)
        # an input the job no longer declares is no change (DVC agrees): what it made came from the inputs it still reads
        changed = sorted(k for k in current if current[k] != record["inputs"].get(k))
        if changed:
            more = f" (and {len(changed) - 1} more)" if len(changed) > 1 else ""
            problem = f"{CHANGED}{changed[0]} changed since it ran{more}"
    return problem


def stale_dvc_yaml(params: dict) -> str | None:
    """None when the dvc.yaml in the working folder is what `vtgen workflow` writes for ``params``; else a warning
    naming the stages that differ and the fix (DVC would run other stages or paths than Snakemake does)."""
    path = DVC_FILES["main"]
    expected = dvc_yaml(params, "main")
    written = path.read_text() if path.is_file() else None
    if written == expected:
        return None
    if written is None:
        difference = "is missing"
    else:
        have = set((yaml.safe_load(written) or {}).get("stages") or {})
        want = set(yaml.safe_load(expected)["stages"])
        parts = [f"lists {', '.join(sorted(have - want))}, which these params do not have"] if have - want else []
        parts += [f"lacks {', '.join(sorted(want - have))}"] if want - have else []
        difference = "; ".join(parts) or "has other commands, paths or params than these params give"
    return (f"vtgen: warning: {path} {difference} (dataset.source is '{params['dataset']['source']}'), so `dvc status` "
            f"and `dvc exp run` would not follow this run: run `vtgen workflow` to rewrite it")


def commit_to_dvc(params: dict) -> str | None:
    """Record in DVC (``dvc commit``) every main-job stage whose outputs match their content records, so that
    ``dvc status`` agrees with the Snakemake run that made them; a line saying what was done (or, when dvc.yaml
    was written for other params, why nothing was), None outside a DVC project."""
    import shutil
    import subprocess
    import time

    from vtgen.io.contents import Hasher

    if not Path(".dvc").is_dir() or shutil.which("dvc") is None:
        return None
    stale = stale_dvc_yaml(params)
    if stale:
        return f"{stale}, then `dvc commit --force` to record this run's stages in DVC (nothing was recorded)"
    started = time.perf_counter()
    hasher = Hasher(".")
    current = [job.name for job in jobs(params, "main") if job_problem(job, params, hasher) is None]
    hasher.save()
    if not current:
        return None
    done = subprocess.run(["dvc", "commit", "--force", *current], capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        return (f"vtgen: warning: `dvc commit` of the finished stages failed ({(done.stderr or done.stdout).strip()}); "
                f"`dvc status` will list them until `dvc commit` succeeds")
    return f"vtgen: {len(current)} finished stages recorded in DVC's cache (dvc commit, {seconds:.1f} s)"


def reconcile(params: dict, root: str | Path = ".") -> list[str]:
    """Make Snakemake's file times say what the content records say (run at the start of a Snakemake run).

    For each job of the main job, upstream first, whose outputs exist and hold a content record:

    * an output that differs from its record (truncated, edited, a file missing or added), or an input whose
      content changed since the job ran (a new, replaced or deleted image below ``dataset.path``), makes the
      job's outputs older than anything (1970), so Snakemake runs it again;
    * a job whose outputs and inputs match the record but look older than an input (after ``dvc pull`` or
      ``dvc checkout``, or a rewritten params record) gets its outputs' times set to now, so Snakemake reuses
      them as DVC does.

    Returns one line per job marked to run again. Outputs without a record (an older vtgen) are left to
    Snakemake's own rules.
    """
    import time

    from vtgen.io.contents import Hasher

    root = Path(root)
    cwd = os.getcwd()
    os.chdir(root)
    lines: list[str] = []
    rerun: set[str] = set()
    try:
        hasher = Hasher(".")
        stamp = time.time_ns()
        for job in jobs(params, "main"):
            problem = job_problem(job, params, hasher)
            if problem in (MISSING, UNRECORDED):
                continue
            if problem is not None:
                _set_mtime(job.outputs, STALE_NS)
                if not problem.startswith(CHANGED) or not any(p in rerun for p in job.inputs):  # not "upstream reruns"
                    lines.append(f"vtgen: {job.name}: {problem}; it runs again")
                rerun.update(job.outputs)
                continue
            newest = max((t for p in (*job.inputs, params_record(job.stage, job.wildcards)) if (t := _snakemake_mtime(p))),
                         default=0)
            if any((_snakemake_mtime(p) or 0) < newest for p in job.outputs):
                stamp = max(time.time_ns(), stamp + 1000)
                _set_mtime(job.outputs, stamp)
        hasher.save()
    finally:
        os.chdir(cwd)
    return lines


def record_job(job: Job, inputs: dict[str, str | None]) -> None:
    """Write ``job``'s content record (inputs as hashed when it started, outputs as they are now); run from the
    project root, as both tools run stage commands."""
    from vtgen.io.contents import Hasher, write_record

    write_record(job.record_dir, job.name, inputs, list(job.outputs), Hasher("."))
