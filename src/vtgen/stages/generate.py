"""Generate stage and the `translate` command: run trained generators on images.

``run_generate`` translates every test-split input tile of a direction (and a share of the
training inputs, for augmented classification) with the model of each scope entry, and writes
PNGs plus ``generated.parquet`` linking each output to its input and, where the pair is an
aligned view, its ground truth. ``translate_files`` serves any image or folder a user gives.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import torch
import torch.nn.functional as F
from PIL import Image
from tqdm import tqdm

from vtgen.core.conditioning import Conditioning
from vtgen.core.readers import fit_feature_reader
from vtgen.io.images import atomic_output_dir, display_path, labelled_sheet, read_rgb8, stream_map, write_png
from vtgen.io.tables import read_table
from vtgen.core.translation import translate  # noqa: F401 (also this stage's public name)
from vtgen.core.roi import image_tiles
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.io.tables import GENERATED_COLUMNS, READ_SPLIT
from vtgen.io.checkpoints import load_translator

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".npy"}


def select_inputs(splits: pd.DataFrame, pairs: pd.DataFrame, direction: str, scope: str, train_share: float,
                  seed: int) -> pd.DataFrame:
    """Input tiles to translate: every test-split input of the scope, plus ``train_share`` of each class's
    training inputs (drawn with ``seed``). Columns: split, class, input_path, ground_truth_path."""
    source_mod = DIRECTIONS[direction][0]
    inputs = splits[(splits["modality"] == source_mod) & splits["split"].isin(["train", "test"])]
    if scope != "all":
        inputs = inputs[inputs["class"] == scope]
    rng = np.random.default_rng(seed)
    chosen = [inputs[inputs["split"] == "test"]]
    for _, group in inputs[inputs["split"] == "train"].groupby("class", sort=True):
        keep = int(round(train_share * len(group)))
        chosen.append(group.iloc[np.sort(rng.choice(len(group), size=keep, replace=False))])
    selected = pd.concat(chosen).sort_values(["split", "class", "path"]).rename(columns={"path": "input_path"})
    aligned = pairs[pairs["aligned"]]
    truth = dict(zip(aligned["input_path"], aligned["target_path"]))
    selected["ground_truth_path"] = [truth.get(path, "") for path in selected["input_path"]]
    return selected[["split", "class", "input_path", "ground_truth_path"]].reset_index(drop=True)


def comparison_sheet(rows: pd.DataFrame, image_root: Path, per_class: int = 4,
                     real_examples: dict[str, list[str]] | None = None,
                     other_draws: dict[str, list[np.ndarray]] | None = None,
                     read_names: dict[str, str] | None = None) -> np.ndarray:
    """One row per class: inputs | generated (``output_name`` under ``image_root``) | ground truth where the
    pair is aligned, else ``real_examples[class]`` (real target-modality images of the class, not partners of
    the inputs: what generated images of the class should look like); grey when neither exists.
    ``other_draws`` (output_name -> images of the same input under other latent codes) adds one group per draw;
    ``read_names`` (output_name -> the name of the same input's output told the class read from it,
    :func:`read_class_outputs`) adds a group after them."""
    def read(path) -> np.ndarray | None:
        return np.asarray(Image.open(path).convert("RGB")) if path else None

    real_examples, other_draws, read_names = real_examples or {}, other_draws or {}, read_names or {}
    k = max((len(v) for v in other_draws.values()), default=0)
    sheet_rows = []
    for cls, group in rows.groupby("class", sort=True):
        group = group.head(per_class)
        truths = list(group["ground_truth_path"])
        if not any(truths):
            truths = (list(real_examples.get(cls, [])) + [""] * per_class)[:len(group)]
        draws = [[(other_draws.get(n) or [None] * k)[d] for n in group["output_name"]] for d in range(k)]
        if read_names:
            draws.append([read(image_root / read_names[n]) if n in read_names else None for n in group["output_name"]])
        sheet_rows.append((cls, [[read(p) for p in group["input_path"]],
                                 [read(image_root / n) for n in group["output_name"]], *draws,
                                 [read(p) for p in truths]]))
    titles = ["input", "generated", *[f"generated, code {d + 2}" for d in range(k)],
              *(["told the class read"] if read_names else []), "ground truth, or real of the class"]
    return labelled_sheet(sheet_rows, titles, per_class)


def other_codes(generator: torch.nn.Module, meta: dict, rows: pd.DataFrame, per_class: int = 4,
                codes: int = 2, truncation: float = 1.0) -> dict[str, list[np.ndarray]]:
    """For the first ``per_class`` rows of each class (the preview's inputs), ``codes`` more translations
    under other latent codes (``translate`` seeds 10**6, 10**6 + 1, ...; the written images use their batch start),
    scaled by the same ``truncation`` as the written images."""
    shown = rows.groupby("class", sort=True).head(per_class)
    if shown.empty:
        return {}
    inputs = read_tiles(list(shown["input_path"]), meta["size"])
    labels = meta["conditioning"].labels(list(shown["class"]))
    outputs = [translate(generator, inputs, conditioning=meta["conditioning"], labels=labels, seed=10**6 + d,
                         truncation=truncation) for d in range(codes)]
    return {name: [o[i].permute(1, 2, 0).numpy() for o in outputs] for i, name in enumerate(shown["output_name"])}


def real_examples_of(splits: pd.DataFrame, direction: str, per_class: int = 4) -> dict[str, list[str]]:
    """The first ``per_class`` real test tiles (by path) of the direction's target modality, per class."""
    target = DIRECTIONS[direction][1]
    rows = splits[(splits["split"] == "test") & (splits["modality"] == target)].sort_values("path")
    return {cls: list(group["path"].head(per_class)) for cls, group in rows.groupby("class", sort=True)}


def reads_the_class(meta: dict) -> bool:
    """Whether the generate stage also writes :func:`read_class_outputs` for this model: a generator told each
    input's true class (conditioning ``class``) under the class-pair objective, of two classes or more."""
    conditioning = meta["conditioning"]
    return conditioning.kind == "class" and meta.get("objective") == "class_gan" and len(conditioning.classes) > 1


def read_output_name(output_name: str) -> str:
    """Where :func:`read_class_outputs` writes the image of the test output ``output_name``
    (images/<scope>/test/... -> images/<scope>/test_read/...)."""
    parts = Path(output_name).parts
    return str(Path(*parts[:2], READ_SPLIT, *parts[3:]))


def class_reader(meta: dict, splits: pd.DataFrame, direction: str) -> torch.nn.Module:
    """The reader of :func:`read_class_outputs`: a hand-crafted-feature reader
    (:func:`vtgen.core.readers.fit_feature_reader`) fitted on the training inputs of the model's classes, what
    ``conditioning: inferred`` with ``translation.inferred_reader: features`` would be told by."""
    conditioning = meta["conditioning"]
    train = splits[(splits["modality"] == DIRECTIONS[direction][0]) & (splits["split"] == "train")
                   & splits["class"].isin(conditioning.classes)].sort_values("path")
    return fit_feature_reader(read_tiles(list(train["path"]), meta["size"]),
                              conditioning.labels(list(train["class"])), len(conditioning.classes))


def read_class_outputs(generator: torch.nn.Module, meta: dict, reader: torch.nn.Module, chunk: pd.DataFrame,
                       inputs: torch.Tensor, seed: int, truncation: float) -> tuple[list[np.ndarray], int]:
    """The test rows of one batch ``chunk`` (its ``inputs``) of a generator told the class (:func:`reads_the_class`),
    translated told instead the class ``reader`` (:func:`class_reader`) reads from each: what a generator not told
    the class can at best be (issue 24, goal 3); the classify stage scores them as a second GAN-test. The whole
    batch is translated with the plain outputs' ``seed``, so each input keeps its latent code and one read as its
    own class gets the identical image. Returns (the test rows' images, H x W x 3 uint8; how many were read right)."""
    conditioning = meta["conditioning"]
    test = torch.tensor((chunk["split"] == "test").to_numpy())
    truth = conditioning.labels(list(chunk["class"]))
    with torch.no_grad():
        read = torch.where(test, reader(inputs).argmax(dim=1), truth)
    images = translate(generator, inputs, conditioning=conditioning, labels=read, seed=seed, truncation=truncation)
    return [image.permute(1, 2, 0).numpy() for image in images[test]], int((read[test] == truth[test]).sum())


def _training_status(model_dir: Path) -> str:
    """The train stage's status of one model folder ("ok" when it holds a model)."""
    record = model_dir / "train.json"
    if not (model_dir / "generator.pt").is_file() and record.is_file():
        return json.loads(record.read_text()).get("status", "ok")
    return "ok"


def run_generate(params: dict, direction: str, pairs_dir: str | Path, models_dir: str | Path, out_dir: str | Path,
                 progress: bool = True) -> dict:
    """Stage entry: translate with ``models_dir/<scope>/generator.pt`` for every translation.scope entry.

    Writes ``images/<scope>/<split>/<class>/<name>.png``, ``generated.parquet`` (GENERATED_COLUMNS;
    ground_truth_path is empty where the pair is not an aligned view), ``preview.png`` and
    ``summary.json`` into ``out_dir`` atomically. For a generator told the class under the class-pair objective
    it also writes the test inputs told the class read from them (:func:`read_class_outputs`: split
    :data:`READ_SPLIT`, summary ``told_the_class_read``: reader, inputs, read_correctly, read_accuracy).
    """
    cfg = params["generate"]
    truncation = cfg["truncation"][direction] if isinstance(cfg["truncation"], dict) else cfg["truncation"]
    pairs_dir, models_dir, out_dir = Path(pairs_dir), Path(models_dir), Path(out_dir)
    pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    tables, summary, draws = [], {"direction": direction, "scopes": {}}, {}
    read_of: dict[str, str] = {}  # a test output's name -> its name told the class read (read_class_outputs)
    with atomic_output_dir(out_dir) as tmp:
        for scope in params["translation"]["scope"]:
            status = _training_status(models_dir / scope)
            if status.startswith("not applicable"):
                summary["scopes"][scope] = {"status": status, "train": 0, "test": 0, "with_ground_truth": 0}
                continue
            generator, meta = load_translator(models_dir / scope, params["translation"]["device"])
            if meta["direction"] != direction:
                raise ValueError(f"{meta['path']}: model translates {meta['direction']}, not {direction}")
            rows = select_inputs(splits, pairs, direction, scope, cfg["train_share"], cfg["seed"])
            rows["output_name"] = [f"images/{scope}/{split}/{cls}/{Path(path).stem}.png"
                                   for split, cls, path in zip(rows["split"], rows["class"], rows["input_path"])]
            reader = class_reader(meta, splits, direction) if reads_the_class(meta) else None
            read_right = 0
            for start in tqdm(range(0, len(rows), cfg["batch_size"]), desc=f"generate {direction}/{scope}",
                              unit="batch", disable=not progress, mininterval=1.0):
                chunk = rows.iloc[start:start + cfg["batch_size"]]
                inputs = read_tiles(list(chunk["input_path"]), meta["size"])
                outputs = translate(generator, inputs, conditioning=meta["conditioning"],
                                    labels=meta["conditioning"].labels(list(chunk["class"])), seed=start,
                                    truncation=truncation)
                written = [(name, image.permute(1, 2, 0).numpy()) for name, image in zip(chunk["output_name"], outputs)]
                if reader is not None and (chunk["split"] == "test").any():
                    images, right = read_class_outputs(generator, meta, reader, chunk, inputs, start, truncation)
                    plain = list(chunk.loc[chunk["split"] == "test", "output_name"])
                    read_of.update((n, read_output_name(n)) for n in plain)
                    written += list(zip((read_of[n] for n in plain), images))
                    read_right += right
                for name, image in written:
                    (tmp / name).parent.mkdir(parents=True, exist_ok=True)
                    write_png(tmp / name, image)
            if generator.latent and truncation > 0:  # at psi 0 every draw is the mean code's: nothing more to show
                draws.update(other_codes(generator, meta, rows[rows["split"] == "test"], truncation=truncation))
            read_summary = None
            if reader is not None:
                test_rows = rows[rows["split"] == "test"]
                told_read = test_rows.assign(split=READ_SPLIT, output_name=test_rows["output_name"].map(read_of))
                rows = pd.concat([rows, told_read], ignore_index=True)
                read_summary = {"reader": "features", "inputs": len(test_rows), "read_correctly": read_right,
                                "read_accuracy": round(read_right / len(test_rows), 6) if len(test_rows) else None}
            rows["output_path"] = [str(out_dir / n) for n in rows["output_name"]]
            rows["direction"], rows["scope"], rows["model"] = direction, scope, str(models_dir / scope / "generator.pt")
            tables.append(rows)
            summary["scopes"][scope] = {s: int((rows["split"] == s).sum()) for s in ("train", "test")}
            summary["scopes"][scope]["conditioning"] = meta["conditioning"].kind
            plain_rows = rows[rows["split"] != READ_SPLIT]
            summary["scopes"][scope]["with_ground_truth"] = int((plain_rows["ground_truth_path"] != "").sum())
            if read_summary is not None:
                summary["scopes"][scope]["told_the_class_read"] = read_summary
            if generator.latent and truncation != 1.0:  # the plain draw adds no key: the default's summary stays as it was
                summary["scopes"][scope]["truncation"] = truncation
        table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame(columns=GENERATED_COLUMNS)
        table[GENERATED_COLUMNS].to_parquet(tmp / "generated.parquet", index=False)
        if tables:
            write_png(tmp / "preview.png", comparison_sheet(table[table["split"] == "test"], tmp,
                                                            real_examples=real_examples_of(splits, direction),
                                                            other_draws=draws, read_names=read_of))
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for scope, counts in summary["scopes"].items():
        print(f"generate {direction}/{scope}: {counts['test']} test and {counts['train']} training inputs translated "
              f"({counts['with_ground_truth']} with ground truth) -> {out_dir}")
        read = counts.get("told_the_class_read")
        if read:
            print(f"generate {direction}/{scope}: the {read['inputs']} test inputs also translated told the class a "
                  f"hand-crafted-feature reader reads from each (read right for {read['read_correctly']}), for goal 3's "
                  f"GAN-test of a generator not told the class")
    return summary


def _read_user_image(path: Path) -> tuple[np.ndarray, str]:
    """A user's image as ((H, W, 3) uint8, conversion note), or ImageError/ValueError
    saying what is wrong. Images go through :func:`read_rgb8` (greyscale, 16-bit, palette and alpha are
    converted, with a note); ``.npy`` arrays must be H x W x 3, uint8 or float in [0, 1]."""
    if path.suffix.lower() != ".npy":
        decoded = read_rgb8(path)
        return decoded.rgb, decoded.note
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"cannot read as a numpy array ({exc})") from exc
    if array.ndim != 3 or array.shape[2] != 3:
        raise ValueError(f"expected an H x W x 3 array, got shape {array.shape}")
    if array.dtype == np.uint8:
        return array, ""
    if np.issubdtype(array.dtype, np.floating):
        if not np.isfinite(array).all():
            raise ValueError("array holds NaN or infinite values")
        if array.min() < 0 or array.max() > 1:
            raise ValueError(f"float values must lie in [0, 1], got [{array.min():.4g}, {array.max():.4g}]")
        return np.round(array * 255).astype(np.uint8), ""
    raise ValueError(f"unsupported array type {array.dtype} (use uint8 in [0, 255] or float in [0, 1])")


def _resize_tiles(tiles: list[np.ndarray], size: int) -> list[np.ndarray]:
    """Square RGB tiles to ``size`` x ``size`` exactly as the train stage's tile reader resizes them
    (area when shrinking, bilinear when enlarging)."""
    out = []
    for tile in tiles:
        if tile.shape[:2] != (size, size):
            batch = torch.from_numpy(np.ascontiguousarray(tile)).permute(2, 0, 1)[None].float()
            shrink = tile.shape[0] > size
            batch = F.interpolate(batch, size=(size, size), mode="area" if shrink else "bilinear",
                                  align_corners=None if shrink else False)
            tile = batch.round().clamp(0, 255).to(torch.uint8)[0].permute(1, 2, 0).numpy()
        out.append(tile)
    return out


def prepare_input(image: np.ndarray, meta: dict, as_tiles: bool = False) -> tuple[list[np.ndarray], list[str]]:
    """The model inputs (uint8 size x size x 3 tiles) cut from one user image, and notes on what was done.

    With a recorded preparation (``meta["preparation"]``): the image is brought to the training
    inputs' channels (colour -> greyscale for a model trained on greyscale sources, with a note;
    greyscale given to a colour model is noted), then the recorded ROI rule cuts its tiles (skipped
    with ``as_tiles``), which are resized to the model size. Without one (older model files), the
    image must already be a tile of the model size. Raises ValueError saying why the image cannot
    be prepared (it gives no tile, or has the wrong size).
    """
    size, preparation, notes = meta["size"], meta["preparation"], []
    if preparation is None:
        if image.shape[:2] != (size, size):
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}, the model needs {size}x{size} "
                             f"(cut tiles with the roi stage or resize first; this model file records no "
                             f"input preparation)")
        return [image], notes
    is_grey = bool((image[..., 0] == image[..., 1]).all() and (image[..., 1] == image[..., 2]).all())
    if preparation["input_channels"] == 1 and not is_grey:
        image = np.repeat(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)[:, :, None], 3, axis=2)
        notes.append("colour converted to greyscale (the model was trained on greyscale inputs)")
    elif preparation["input_channels"] == 3 and is_grey:
        notes.append("greyscale input to a model trained on colour inputs")
    if as_tiles:
        if image.shape[0] != image.shape[1]:
            raise ValueError(f"image is {image.shape[1]}x{image.shape[0]}: a tile must be square")
        return _resize_tiles([image], size), notes
    # the ROI rule the roi stage applies to every dataset image (vtgen.core.roi.image_tiles)
    _, tiles, reason = image_tiles(image, preparation["input_modality"], preparation["roi"])
    if reason:
        raise ValueError(reason)
    return _resize_tiles(tiles, size), notes


def collect_inputs(inputs: list[str | Path], out_dir: Path) -> list[tuple[Path, Path]]:
    """(file, relative output stem) for every input: a file argument gives its own name, a folder
    argument every image under it (recursively, ``IMAGE_SUFFIXES``, skipping ``out_dir`` if it lies
    inside) at its path relative to that folder. FileNotFoundError/ValueError for a missing input or
    a folder without images."""
    out_resolved = out_dir.resolve()
    found: list[tuple[Path, Path]] = []
    for item in map(Path, inputs):
        if item.is_dir():
            files = sorted(p for p in item.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file()
                           and not p.resolve().is_relative_to(out_resolved))
            if not files:
                raise ValueError(f"{item}: no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in this folder or below")
            found.extend((p, p.relative_to(item).with_suffix("")) for p in files)
        elif item.is_file():
            found.append((item, Path(item.stem)))
        else:
            raise FileNotFoundError(f"{item}: no such file or folder")
    return list(dict.fromkeys(found))  # the same file named twice the same way is translated once


def _output_collisions(found: list[tuple[Path, Path]], out_dir: Path) -> list[tuple[Path, str]]:
    """Problems for inputs whose outputs would land on the same file (``x.png`` and ``x.jpg``, or two
    file arguments of one name), each naming the other input."""
    first: dict[Path, Path] = {}
    problems = []
    for path, stem in found:
        if stem in first:
            problems.append((path, f"its output {out_dir / stem}.png would overwrite that of {first[stem]}"))
        else:
            first[stem] = path
    return problems


def _refusal(problems: list[tuple[Path, str]], total: int) -> ValueError:
    if total == 1 and len(problems) == 1:
        return ValueError(f"{display_path(problems[0][0])}: {problems[0][1]}")
    lines = "\n".join(f"  {display_path(path)}: {reason}" for path, reason in problems)
    return ValueError(f"{len(problems)} problem{'s' if len(problems) > 1 else ''} in {total} inputs; "
                      f"nothing translated:\n{lines}")


def translate_files(model: str | Path, inputs: list[str | Path], out_dir: str | Path, device: str = "cpu",
                    direction: str | None = None, as_tiles: bool = False, progress: bool | None = None,
                    batch_size: int = 32, class_name: str | None = None) -> list[Path]:
    """Translate user images (files, or folders searched recursively) and return the PNGs written.

    Each image is prepared as the model's training inputs were (:func:`prepare_input`: the ROI rule
    recorded in the model file cuts its tiles; older model files need tiles of the model size).
    Outputs keep the input's path relative to its folder argument (a file argument: its name):
    ``<out_dir>/<rel>.png``, or ``<rel>_<k>.png`` for an image that gives several tiles.
    All or nothing: every input is read and prepared; when any cannot be, or two outputs would
    share a file, one ValueError lists every such input with its reason and nothing is written.
    Outputs are staged beside ``out_dir`` and moved in only when every input succeeded.
    ``direction``, when given, must match the model. ``progress`` (default: for 20 inputs or more)
    shows a progress bar on stderr. A model conditioned on the class needs ``class_name`` (one of the
    classes it was trained on), which every input is asked to be.
    """
    generator, meta, label = _open_translator(model, device, direction, class_name)
    conditioning = meta["conditioning"]
    out_dir = Path(out_dir)
    found = collect_inputs(inputs, out_dir)
    problems = _output_collisions(found, out_dir)
    collided = {path for path, _ in problems}
    if meta["note"]:
        print(f"translate: note: {meta['note']}")
    staging = out_dir.parent / f".{out_dir.name}.translate-{os.getpid()}.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    owner: dict[Path, Path] = {}  # output name (relative) -> input, to catch x_0.png meeting a file named x_0
    notes: dict[str, list[Path]] = {}
    pending: list[tuple[Path, np.ndarray]] = []
    written: list[Path] = []
    frames = 0

    def flush() -> None:
        if pending and not problems:
            batch = torch.from_numpy(np.stack([tile for _, tile in pending])).permute(0, 3, 1, 2).contiguous()
            labels = None if label is None else label.repeat(len(batch))
            for (name, _), image in zip(pending, translate(generator, batch, batch_size, conditioning, labels)):
                (staging / name).parent.mkdir(parents=True, exist_ok=True)
                write_png(staging / name, image.permute(1, 2, 0).numpy())
                written.append(name)
        pending.clear()

    show = len(found) >= 20 if progress is None else progress
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # two reader threads are the parallelism; OpenCV's own pool on top only adds contention
    try:
        prepare = functools.partial(_prepare_user_file, meta=meta, as_tiles=as_tiles)
        for path, stem, tiles, text in stream_map(prepare, found, workers=2, total=len(found), desc="translate",
                                                  progress=show):
            if tiles is None:
                problems.append((path, text))
                continue
            if text:
                notes.setdefault(text, []).append(path)
            names = _output_names(stem, len(tiles))
            clashes = [name for name in names if name in owner and owner[name] != path]
            if clashes and path not in collided:
                problems.append((path, f"its output {out_dir / clashes[0]} would overwrite that of {owner[clashes[0]]}"))
            owner.update({name: path for name in names})
            frames += 1
            pending.extend(zip(names, tiles))
            if len(pending) >= batch_size:
                flush()
        if problems:
            raise _refusal(problems, len(found))
        flush()
        _move_outputs(staging, out_dir, written)
    finally:
        cv2.setNumThreads(opencv_threads)
        shutil.rmtree(staging, ignore_errors=True)
    _print_summary(meta, notes, frames, len(written), out_dir, as_tiles)
    return [out_dir / name for name in written]


def _open_translator(model: str | Path, device: str, direction: str | None, class_name: str | None):
    """(generator, model facts, the class label every input is asked to be or None) of the model file;
    ValueError naming the file when it translates another ``direction`` or needs a ``class_name``."""
    generator, meta = load_translator(model, device)
    if direction and direction != meta["direction"]:
        raise ValueError(f"{meta['path']}: model translates {meta['direction']}, not {direction}")
    conditioning = meta["conditioning"]
    if conditioning.needs_labels and class_name is None:
        raise ValueError(f"{meta['path']}: this model is conditioned on the class ({conditioning.kind}); name the "
                         f"class of the inputs with --class (one of {', '.join(conditioning.classes)})")
    label = conditioning.labels([class_name])[0] if conditioning.needs_labels else None
    return generator, meta, label


def _prepare_user_file(item: tuple[Path, Path], meta: dict, as_tiles: bool):
    """(path, stem, the model-ready tiles or None, its notes joined or the reason it cannot be used) of one
    input file (:func:`prepare_input`)."""
    path, stem = item
    try:
        image, note = _read_user_image(path)
        tiles, extra = prepare_input(image, meta, as_tiles)
    except (ValueError, cv2.error) as exc:  # ImageError is a ValueError
        return path, stem, None, str(exc)
    return path, stem, tiles, "; ".join(n for n in [note, *extra] if n)


def _move_outputs(staging: Path, out_dir: Path, written: list[Path]) -> None:
    """Move every staged output (relative name in ``written``) to the same name under ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name in written:
        (out_dir / name).parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging / name, out_dir / name)


def _output_names(stem: Path, tiles: int) -> list[Path]:
    """The output file names (relative) of an input giving ``tiles`` tiles: ``<stem>.png`` or ``<stem>_<k>.png``."""
    return ([stem.with_name(f"{stem.name}.png")] if tiles == 1
            else [stem.with_name(f"{stem.name}_{k}.png") for k in range(tiles)])


def _print_summary(meta: dict, notes: dict[str, list[Path]], frames: int, tiles: int, out_dir: Path,
                   as_tiles: bool) -> None:
    """The conversion notes (one line per note, naming its first input) and what was translated how."""
    for text, paths in sorted(notes.items()):
        print(f"translate: note: {len(paths)} input{'s' if len(paths) > 1 else ''} ({display_path(paths[0])}"
              f"{', ...' if len(paths) > 1 else ''}): {text}")
    prep = meta["preparation"]
    how = ("as tiles, resized to the model size" if as_tiles else
           f"{prep['input_modality']} ROI rule: {_describe_roi(prep['roi'])}" if prep else "as tiles of the model size")
    print(f"translate ({meta['direction']}): {frames} images -> {tiles} tiles of {meta['size']} px "
          f"({how}) -> {out_dir}")


def _describe_roi(roi: dict) -> str:
    crop = (f"centre crop {roi['crop_fraction']}" if roi["visual_crop"] == "centre"
            else f"grid of tiles {roi['crop_fraction']}")
    return (f"tactile_box {roi['tactile_box']}, markers {'removed' if roi['remove_markers'] else 'kept'}, "
            f"{crop}, {roi['size']} px")
