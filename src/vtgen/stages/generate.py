"""Generate stage and the `translate` command: run trained generators on images.

``run_generate`` translates every test-split input tile of a direction (and a share of the
training inputs, for augmented classification) with the model of each scope entry, and writes
PNGs plus ``generated.parquet`` linking each output to its input and, where the pair is an
aligned view, its ground truth. ``translate_files`` serves any image or folder a user gives.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from PIL import Image
from tqdm import tqdm

from vtgen.core.gan import to_model_range, to_uint8
from vtgen.io.images import atomic_output_dir, labelled_sheet, write_png
from vtgen.io.tables import read_table
from vtgen.core.models import UNetGenerator
from vtgen.core.domain import DIRECTIONS
from vtgen.io.tables import PAIR_COLUMNS, SPLIT_COLUMNS
from vtgen.io.images import read_tiles
from vtgen.io.tables import GENERATED_COLUMNS
from vtgen.io.checkpoints import load_translator

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".npy"}
@torch.no_grad()
def translate(generator: UNetGenerator, images: torch.Tensor, batch_size: int = 32) -> torch.Tensor:
    """uint8 N x 3 x S x S -> uint8 N x 3 x S x S through ``generator`` (eval mode, no dropout)."""
    device = next(generator.parameters()).device
    out = [to_uint8(generator(to_model_range(images[i:i + batch_size]).to(device))).cpu()
           for i in range(0, len(images), batch_size)]
    return torch.cat(out) if out else images.clone()


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


def comparison_sheet(rows: pd.DataFrame, image_root: Path, per_class: int = 4) -> np.ndarray:
    """One row per class: inputs | generated (``output_name`` under ``image_root``) | ground truth (grey when none)."""
    def read(path) -> np.ndarray | None:
        return np.asarray(Image.open(path).convert("RGB")) if path else None

    sheet_rows = []
    for cls, group in rows.groupby("class", sort=True):
        group = group.head(per_class)
        sheet_rows.append((cls, [[read(p) for p in group["input_path"]],
                                 [read(image_root / n) for n in group["output_name"]],
                                 [read(p) for p in group["ground_truth_path"]]]))
    return labelled_sheet(sheet_rows, ["input", "generated", "ground truth"], per_class)


def run_generate(params: dict, direction: str, pairs_dir: str | Path, models_dir: str | Path, out_dir: str | Path,
                 progress: bool = True) -> dict:
    """Stage entry: translate with ``models_dir/<scope>/generator.pt`` for every translation.scope entry.

    Writes ``images/<scope>/<split>/<class>/<name>.png``, ``generated.parquet`` (GENERATED_COLUMNS;
    ground_truth_path is empty where the pair is not an aligned view), ``preview.png`` and
    ``summary.json`` into ``out_dir`` atomically.
    """
    cfg = params["generate"]
    pairs_dir, models_dir, out_dir = Path(pairs_dir), Path(models_dir), Path(out_dir)
    pairs = read_table(pairs_dir / f"{direction}.parquet", PAIR_COLUMNS, f"a {direction} pair table")
    splits = read_table(pairs_dir / "splits.parquet", SPLIT_COLUMNS, "the split table of the pairs stage")
    tables, summary = [], {"direction": direction, "scopes": {}}
    with atomic_output_dir(out_dir) as tmp:
        for scope in params["translation"]["scope"]:
            generator, meta = load_translator(models_dir / scope, params["translation"]["device"])
            if meta["direction"] != direction:
                raise ValueError(f"{meta['path']}: model translates {meta['direction']}, not {direction}")
            rows = select_inputs(splits, pairs, direction, scope, cfg["train_share"], cfg["seed"])
            rows["output_name"] = [f"images/{scope}/{split}/{cls}/{Path(path).stem}.png"
                                   for split, cls, path in zip(rows["split"], rows["class"], rows["input_path"])]
            for start in tqdm(range(0, len(rows), cfg["batch_size"]), desc=f"generate {direction}/{scope}",
                              unit="batch", disable=not progress, mininterval=1.0):
                chunk = rows.iloc[start:start + cfg["batch_size"]]
                outputs = translate(generator, read_tiles(list(chunk["input_path"]), meta["size"]))
                for name, image in zip(chunk["output_name"], outputs):
                    (tmp / name).parent.mkdir(parents=True, exist_ok=True)
                    write_png(tmp / name, image.permute(1, 2, 0).numpy())
            rows["output_path"] = [str(out_dir / n) for n in rows["output_name"]]
            rows["direction"], rows["scope"], rows["model"] = direction, scope, str(models_dir / scope / "generator.pt")
            tables.append(rows)
            summary["scopes"][scope] = {s: int((rows["split"] == s).sum()) for s in ("train", "test")}
            summary["scopes"][scope]["with_ground_truth"] = int((rows["ground_truth_path"] != "").sum())
        table = pd.concat(tables, ignore_index=True)
        table[GENERATED_COLUMNS].to_parquet(tmp / "generated.parquet", index=False)
        write_png(tmp / "preview.png", comparison_sheet(table[table["split"] == "test"], tmp))
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    for scope, counts in summary["scopes"].items():
        print(f"generate {direction}/{scope}: {counts['test']} test and {counts['train']} training inputs translated "
              f"({counts['with_ground_truth']} with ground truth) -> {out_dir}")
    return summary


def _read_user_image(path: Path, size: int) -> np.ndarray:
    """A user's image as (size, size, 3) uint8, or a ValueError that says what is wrong with it."""
    if path.suffix.lower() == ".npy":
        array = np.load(path, allow_pickle=False)
        if array.ndim != 3 or array.shape[2] != 3:
            raise ValueError(f"{path}: expected an H x W x 3 array, got shape {array.shape}")
        if array.dtype == np.uint8:
            pass
        elif np.issubdtype(array.dtype, np.floating):
            if not np.isfinite(array).all():
                raise ValueError(f"{path}: array holds NaN or infinite values")
            if array.min() < 0 or array.max() > 1:
                raise ValueError(f"{path}: float values must lie in [0, 1], got [{array.min():.4g}, {array.max():.4g}]")
            array = np.round(array * 255).astype(np.uint8)
        else:
            raise ValueError(f"{path}: unsupported array type {array.dtype} (use uint8 in [0, 255] or float in [0, 1])")
    else:
        try:
            with Image.open(path) as image:
                image.load()
                if image.mode != "RGB":
                    raise ValueError(f"{path}: image mode is {image.mode}; the model needs 8-bit RGB "
                                     f"(convert it, e.g. PIL's Image.convert('RGB'))")
                array = np.asarray(image)
        except (OSError, Image.DecompressionBombError) as exc:
            raise ValueError(f"{path}: cannot read as an image ({exc})") from exc
    if array.shape[:2] != (size, size):
        raise ValueError(f"{path}: image is {array.shape[1]}x{array.shape[0]}, the model needs {size}x{size} "
                         f"(cut tiles with the roi stage or resize first)")
    return array


def translate_files(model: str | Path, inputs: list[str | Path], out_dir: str | Path, device: str = "cpu",
                    direction: str | None = None) -> list[Path]:
    """Translate user images (files or folders of them) and write ``<out_dir>/<name>.png`` for each.

    Every image is checked before any is translated: it must be 8-bit RGB (or an .npy array,
    uint8 or float in [0, 1]) of the model's size. ``direction``, when given, must match the model.
    """
    generator, meta = load_translator(model, device)
    if direction and direction != meta["direction"]:
        raise ValueError(f"{meta['path']}: model translates {meta['direction']}, not {direction}")
    files: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted(p for p in item.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
            if not found:
                raise ValueError(f"{item}: no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in this folder")
            files.extend(found)
        elif item.is_file():
            files.append(item)
        else:
            raise FileNotFoundError(f"{item}: no such file or folder")
    arrays = [_read_user_image(p, meta["size"]) for p in files]
    outputs = translate(generator, torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous())
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for path, image in zip(files, outputs):
        target = out_dir / f"{path.stem}.png"
        write_png(target, image.permute(1, 2, 0).numpy())
        written.append(target)
    print(f"translate ({meta['direction']}): {len(written)} images -> {out_dir}")
    return written
