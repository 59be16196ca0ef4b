"""Command-line entry: one subcommand per pipeline stage.

Snakemake rules and DVC stages run exactly these commands, e.g.
``vtgen ingest --params params.yaml --out data/ingest``. Each stage reads its section of
params.yaml, reads only the inputs named on its command line and writes one output folder
atomically. Errors are reported in one line naming the file and the problem; set
``VTGEN_DEBUG=1`` for a traceback.

Pipeline stages take the project's run lock (:mod:`vtgen.io.runlock`) and record their wall time in
``timing.json`` inside their output folder, where the report finds the timings of the very
outputs it reports. Neither DVC (.dvcignore) nor the content records hash that file, so a stage that runs
again and writes the same data does not make the stages after it run again (:mod:`vtgen.io.timing`).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from contextlib import contextmanager
from pathlib import Path

from vtgen.core.domain import DIRECTIONS
from vtgen.io.params import AUTO_RECIPE, ParamsError, load_params, recipe_choice, with_recipe


def _render(args, params) -> None:
    from vtgen.stages.render import render_dataset

    source = params["dataset"]["source"]
    if source != "synthetic":  # only a dvc.yaml written for another source runs this stage (Snakemake leaves it out)
        raise ValueError(f"{args.params}: dataset.source is '{source}', so the main job has no render stage, but it "
                         f"was asked to run (a dvc.yaml written for the synthetic dataset still lists it): run "
                         f"`vtgen workflow` to rewrite dvc.yaml for this source, then run again")
    cfg = params["synthetic"]
    info = render_dataset(Path(args.out), cfg["classes"], cfg["samples_per_class"], cfg["size"],
                          cfg["aligned"], cfg["seed"], workers=cfg["workers"])
    print(f"render: SYNTHETIC dataset, {len(cfg['classes'])} classes x {cfg['samples_per_class']} samples "
          f"x 2 modalities at {cfg['size']} px in {info['seconds']:.1f} s -> {args.out}")


def _ingest(args, params) -> None:
    from vtgen.stages.ingest import run_ingest

    run_ingest(params["dataset"]["path"], params["dataset"], args.out, params["ingest"]["workers"])


def _roi(args, params) -> None:
    from vtgen.stages.roi import run_roi

    run_roi(args.manifest, params["roi"], args.out, params["ingest"]["workers"])


def _pairs(args, params) -> None:
    from vtgen.stages.pairs import run_pairing

    run_pairing(args.tiles, params["pairing"], args.out)


def _settings(args, params) -> None:
    from vtgen.stages.settings import run_settings

    chosen, reason = args.recipe
    print(f"settings {args.direction}: recipe '{chosen}' ({reason})")
    run_settings(params, args.direction, args.out)


def _train(args, params) -> None:
    from vtgen.stages.train import run_train

    run_train(params, args.direction, args.scope, args.pairs, args.out, args.checkpoints, tiles_path=args.tiles)


def _generate(args, params) -> None:
    from vtgen.stages.generate import run_generate

    run_generate(params, args.direction, args.pairs, args.models, args.out)


def _translate(args, params) -> None:
    from vtgen.stages.generate import translate_files

    translate_files(args.model, args.inputs, args.out, params["translation"]["device"] if params else "cpu",
                    args.direction, as_tiles=args.tiles, class_name=args.class_name)


def _score(args, params) -> None:
    from vtgen.stages.score import run_score

    run_score(params, args.pairs, args.generated, args.out, args.classify)


def _classify(args, params) -> None:
    from vtgen.stages.classify import run_classify

    run_classify(params, args.modality, args.pairs, args.generated, args.out)


def _report(args, params) -> None:
    from vtgen.stages.report import run_report

    run_report(params, args.ingest, args.pairs, args.models, args.generated, args.scores, args.classify, args.out,
               recipe_reason=args.recipe[1])


def _study(args, params) -> None:
    from vtgen.studies.study import run_variant

    run_variant(params, args.kind, args.name, args.out, args.pairs, args.capacity)


def _frontier(args, params) -> None:
    from vtgen.studies.study import summarise_tradeoff

    summarise_tradeoff(params, args.runs, args.out)


def _stability(args, params) -> None:
    from vtgen.studies.stability import run_stability, write_stability

    write_stability(run_stability(params, args.iterations), args.out)


def _studies_report(args, params) -> None:
    from vtgen.studies.report import run_studies_report

    run_studies_report(params, args.experiments, args.frontier, args.stability, args.out)


def _workflow(args, params) -> None:
    from vtgen.pipeline import DVC_FILES, write_dvc_files

    changed = write_dvc_files(params, Path.cwd(), check=args.check, studies=args.studies)
    if args.check and changed:
        raise ValueError(f"{', '.join(map(str, changed))}: missing or not what the stage table in src/vtgen/pipeline.py "
                         f"writes; run `vtgen workflow{' --studies' if args.studies else ''}` to write them")
    verb = "would change" if args.check else "written"
    following = [str(p) for name, p in DVC_FILES.items() if name == "main" or args.studies or p.is_file()]
    print(f"workflow: {', '.join(map(str, changed)) or 'nothing'} {verb if changed else 'to change'} "
          f"({', '.join(following)} {'follows' if len(following) == 1 else 'follow'} the stage table)")


def _experiments(args, params) -> None:
    import shlex
    import subprocess

    from vtgen.studies.study import dvc_queue_command

    for name, experiment in params["studies"]["experiments"]["runs"].items():
        command = dvc_queue_command(params, name)
        if command is None:
            print(f"# {name}: mode '{experiment['mode']}' runs through the studies pipeline only "
                  f"(snakemake data/studies/experiments/{name})")
            continue
        print(shlex.join(command))
        if args.queue:
            subprocess.run(command, check=True)
    if args.queue:
        print("queued; run them with `dvc queue start` (or `dvc exp run --run-all`), compare with `dvc exp show`")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="vtgen", description="Visual-tactile cross-modal data generation pipeline.")
    sub = parser.add_subparsers(dest="stage", required=True)

    def stage(name, func, help_text):
        p = sub.add_parser(name, help=help_text)
        p.add_argument("--params", default="params.yaml", help="the params file (default: params.yaml)")
        p.add_argument("--out", required=True, help="output folder, replaced atomically")
        p.set_defaults(func=func)
        return p

    stage("render", _render, "render the embedded SYNTHETIC ViTac-like dataset (generic layout)")
    stage("ingest", _ingest, "read dataset.path into manifest.parquet and quarantine tables")
    stage("roi", _roi, "cut manifest images into tiles at roi.size").add_argument(
        "--manifest", required=True, help="manifest.parquet from the ingest stage")
    stage("pairs", _pairs, "assign splits by source and build V2T/T2V pair tables").add_argument(
        "--tiles", required=True, help="tiles.parquet from the roi stage")
    settings = stage("settings", _settings, "write the params values one direction's training reads, resolved")
    settings.add_argument("--direction", required=True, choices=list(DIRECTIONS))
    settings.add_argument("--pairs", required=True, help="folder written by the pairs stage (translation.recipe auto reads it)")
    train = stage("train", _train, "train the conditional GAN of one direction and translation.scope entry")
    train.add_argument("--direction", required=True, choices=list(DIRECTIONS))
    train.add_argument("--scope", required=True, help="'all' or a class name listed in translation.scope")
    train.add_argument("--pairs", required=True, help="folder written by the pairs stage")
    train.add_argument("--tiles", default="data/roi/tiles.parquet",
                       help="tiles.parquet of the roi stage, whose frames class_gan.views crops again "
                            "(default: data/roi/tiles.parquet)")
    train.add_argument("--checkpoints", default="checkpoints",
                       help="root of the resumable checkpoints (default: checkpoints)")
    generate = stage("generate", _generate, "translate the test split (and a share of training inputs)")
    generate.add_argument("--direction", required=True, choices=list(DIRECTIONS))
    generate.add_argument("--pairs", required=True, help="folder written by the pairs stage")
    generate.add_argument("--models", required=True, help="folder holding one trained model per scope entry")
    score = stage("score", _score, "Colour-SSIM, grey SSIM and PSNR of generated images, with reference levels")
    score.add_argument("--pairs", required=True, help="folder written by the pairs stage")
    score.add_argument("--generated", required=True, help="folder holding one generate output per direction")
    score.add_argument("--classify", help="folder of classify/<modality> outputs (their real-only classifiers are "
                                          "a feature view of the distribution metrics)")
    classify = stage("classify", _classify, "texture classifier: real only vs real + generated, per modality")
    classify.add_argument("--modality", required=True, choices=["visual", "tactile"])
    classify.add_argument("--pairs", required=True, help="folder written by the pairs stage")
    classify.add_argument("--generated", required=True, help="folder holding one generate output per direction")
    report = stage("report", _report, "build reports/index.html, summary.md, metrics.json, plots and figures")
    for name, what in (("ingest", "the ingest stage's folder"), ("pairs", "the pairs stage's folder"),
                       ("models", "folder of models/<direction>/<scope>"), ("generated", "folder of generate outputs"),
                       ("scores", "the score stage's folder"), ("classify", "folder of classify/<modality> outputs")):
        report.add_argument(f"--{name}", required=True, help=what)
    study = stage("study", _study, "run one experiment or trade-off setting of params.yaml's studies section")
    study.add_argument("--kind", required=True, choices=["experiments", "tradeoff"])
    study.add_argument("--name", required=True, help="a name under studies.experiments.runs or studies.tradeoff.settings")
    study.add_argument("--pairs", default="data/pairs", help="the main job's pairs folder (default: data/pairs)")
    study.add_argument("--capacity", default=None, help="folder written by `vtgen frontier` (per_class experiments)")
    frontier = stage("frontier", _frontier, "Pareto frontier of the trade-off settings and the capacity-auto choice")
    frontier.add_argument("--runs", required=True, help="folder holding one `vtgen study --kind tradeoff` output per setting")
    stability = stage("stability", _stability, "train at the edges of the parameter space and record each outcome")
    stability.add_argument("--iterations", type=int, default=20, help="training iterations per case (default 20)")
    studies_report = stage("studies-report", _studies_report, "build the experiments, trade-off and stability report")
    studies_report.add_argument("--experiments", required=True, help="folder of `vtgen study --kind experiments` outputs")
    studies_report.add_argument("--frontier", required=True, help="folder written by `vtgen frontier`")
    studies_report.add_argument("--stability", required=True, help="folder written by `vtgen stability`")
    _add_tool_commands(sub)
    return parser


def _add_tool_commands(sub) -> None:
    """The commands that are not pipeline stages: workflow, experiments and translate."""
    workflow = sub.add_parser("workflow", help="write dvc.yaml (and, with --studies, workflow/studies/dvc.yaml) "
                              "from the stage table")
    workflow.add_argument("--params", default="params.yaml")
    workflow.add_argument("--check", action="store_true", help="only check that the files match; exit 2 if not")
    workflow.add_argument("--studies", action="store_true",
                          help="also write workflow/studies/dvc.yaml, the studies for `dvc repro "
                          "workflow/studies/dvc.yaml` (not committed: while it exists, plain `dvc status` lists the "
                          "study stages too; an existing one is always kept current)")
    workflow.set_defaults(func=_workflow)
    experiments = sub.add_parser("experiments", help="print (or queue) the DVC experiments of studies.experiments")
    experiments.add_argument("--params", default="params.yaml")
    experiments.add_argument("--queue", action="store_true", help="run `dvc exp run --queue` for each")
    experiments.set_defaults(func=_experiments)
    translate = sub.add_parser("translate", help="translate your own images or folders with a trained model",
                               description="Prepare each image as the model's training inputs were (the ROI rule "
                               "recorded in the model file), translate every tile, and write PNGs that keep each "
                               "input's path relative to its folder argument. All or nothing: one error lists every "
                               "input that cannot be prepared, and nothing is written.")
    translate.add_argument("inputs", nargs="+", help="raw frames or tiles (PNG, JPEG, BMP, TIFF, WebP or .npy), "
                           "or folders of them (searched recursively)")
    translate.add_argument("--model", required=True, help="a trained model folder (models/<direction>/<scope>) or its generator.pt")
    translate.add_argument("--out", required=True, help="folder for the translated PNGs (<name>.png, or <name>_<k>.png "
                           "for an image that gives several tiles)")
    translate.add_argument("--tiles", action="store_true", help="inputs are already ROI tiles: skip the ROI rule, "
                           "only resize them to the model size")
    translate.add_argument("--direction", choices=list(DIRECTIONS), help="refuse a model of the other direction")
    translate.add_argument("--class", dest="class_name", default=None,
                           help="the class of every input, for a model conditioned on the class (see its train.json)")
    translate.add_argument("--params", default=None, help="params file for translation.device (default: CPU)")
    translate.set_defaults(func=_translate)


PIPELINE_COMMANDS = {"render", "ingest", "roi", "pairs", "settings", "train", "generate", "score", "classify", "report", "study",
                     "frontier", "stability", "studies-report"}


def peak_memory() -> dict:
    """Peak resident memory in MB of this process (``peak_rss_mb``) and of the largest child process it waited for
    (``peak_rss_children_mb``, the stage's worker processes; 0 without any), from getrusage. Linux reports KiB."""
    import resource

    def mb(who: int) -> float:
        return round(resource.getrusage(who).ru_maxrss / 1024, 1)

    return {"peak_rss_mb": mb(resource.RUSAGE_SELF), "peak_rss_children_mb": mb(resource.RUSAGE_CHILDREN)}


def debugging() -> bool:
    """VTGEN_DEBUG=1 (or true, yes, on) shows tracebacks; unset, empty, 0, false, no or off do not."""
    return os.environ.get("VTGEN_DEBUG", "").strip().lower() in ("1", "true", "yes", "on")


# the commands that read values a recipe sets and are given the pairs folder (the stability study reads none: none)
RECIPE_COMMANDS = ("settings", "train", "generate", "report", "study")


def data_kind(args, params) -> dict | None:
    """What ``translation.recipe: auto`` reads (:func:`vtgen.io.params.recipe_choice`): the ``data_kind`` of the
    pairs summary in the ``--pairs`` folder of a command in ``RECIPE_COMMANDS``; None when the recipe is named or
    the command reads no recipe value."""
    if (params["translation"]["recipe"] != AUTO_RECIPE or getattr(args, "stage", None) not in RECIPE_COMMANDS
            or not getattr(args, "pairs", None)):
        return None
    path = Path(args.pairs) / "summary.json"
    if not path.is_file():
        raise ValueError(f"{path}: no pairs summary; translation.recipe 'auto' chooses from it (run the pairs stage first)")
    return json.loads(path.read_text())["data_kind"]


def run_stage(args, params) -> None:
    """Run a pipeline stage under the project's run lock and write its wall time into its output folder."""
    from vtgen.io.runlock import run_lock
    from vtgen.io.timing import TIMING

    started = time.perf_counter()
    with run_lock(f"vtgen {args.stage}"):
        job, inputs = _declared_job(args, params)  # records read params.yaml as written, as DVC does
        kind = data_kind(args, params)
        args.recipe = recipe_choice(params, kind)  # the block applied and why, for the stages that say it
        with threads_as_snakemake(job, params):
            args.func(args, with_recipe(params, kind))
        out = Path(args.out)
        # not reports/ (declared files only) nor a settings folder (its content alone decides whether training reruns)
        if out.is_dir() and args.stage not in ("report", "studies-report", "settings"):
            timing = out / TIMING  # the stage's own times (a training's seconds per step, say), if it wrote any
            record = {**(json.loads(timing.read_text()) if timing.is_file() else {}), "stage": args.stage,
                      "seconds": round(time.perf_counter() - started, 2),
                      "finished": time.strftime("%Y-%m-%dT%H:%M:%S"), **peak_memory()}
            timing.write_text(json.dumps(record) + "\n")
        if job is not None:
            from vtgen.pipeline import record_job

            record_job(job, inputs)


# what Snakemake sets to a job's threads in the environment of its command
THREAD_VARIABLES = ("OMP_NUM_THREADS", "GOTO_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                    "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


@contextmanager
def threads_as_snakemake(job, params):
    """While the block runs outside Snakemake (DVC, or a command typed by hand), give torch, BLAS and child
    processes the job's declared threads, as Snakemake's environment does: a stage that leaves torch at its
    default would otherwise use every core under DVC and one under Snakemake, and its floating-point sums
    (a QR, an SVD) would differ in the last digits. Under Snakemake (OMP_NUM_THREADS set), or for a command
    that is no declared job (``job`` None), nothing changes. Everything is restored afterwards."""
    if job is None or "OMP_NUM_THREADS" in os.environ:
        yield
        return
    import torch
    from threadpoolctl import threadpool_limits

    from vtgen.pipeline import stage_threads

    threads = stage_threads(job.stage, params)
    saved_env, saved_threads = {name: os.environ.get(name) for name in THREAD_VARIABLES}, torch.get_num_threads()
    os.environ.update(dict.fromkeys(THREAD_VARIABLES, str(threads)))
    torch.set_num_threads(threads)
    try:
        with threadpool_limits(threads, user_api="blas"):
            yield
    finally:
        torch.set_num_threads(saved_threads)
        for name, value in saved_env.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _declared_job(args, params):
    """(the stage-table job this command runs, its input hashes now) when ``--out`` is the job's declared output
    under the current folder; (None, None) for a command writing elsewhere."""
    from vtgen.io.contents import Hasher
    from vtgen.pipeline import input_hashes, job_of_command

    if Path(args.out).is_absolute() or not Path("params.yaml").is_file() or not Path(args.params).samefile("params.yaml"):
        return None, None
    job = job_of_command(params, args.stage, args.out)
    return (job, input_hashes(job, params, Hasher("."))) if job is not None else (None, None)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import traceback

    from vtgen.io.images import describe_os_error, display_path

    def fail(message: str, code: int = 2) -> int:
        print(f"vtgen {args.stage}: error: {message}", file=sys.stderr)
        return code

    try:
        try:
            params = load_params(args.params) if args.params else None
        except UnicodeDecodeError as exc:
            raise ParamsError(f"{args.params}: not UTF-8 text ({exc.reason} at byte {exc.start})") from exc
        if args.stage in PIPELINE_COMMANDS:
            run_stage(args, params)
        else:
            args.func(args, params)
    except KeyboardInterrupt:
        print(f"vtgen {args.stage}: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - every failure ends in one line; VTGEN_DEBUG=1 shows the traceback
        if debugging():
            raise
        # bad input, bad configuration, a full disk or an unwritable folder: exit code 2
        if isinstance(exc, OSError):
            return fail(describe_os_error(exc))
        if isinstance(exc, MemoryError):
            return fail("out of memory; use a machine with more memory or smaller settings (see README: Scaling out)")
        if isinstance(exc, (ValueError, RuntimeError)):
            return fail(display_path(str(exc)))
        # anything else is a bug in vtgen: still one line, saying where it happened
        frame = traceback.extract_tb(exc.__traceback__)[-1]
        return fail(f"unexpected {type(exc).__name__}: {display_path(str(exc))} (at {Path(frame.filename).name}:"
                    f"{frame.lineno} in {frame.name}); set VTGEN_DEBUG=1 for the traceback and please report it", code=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
