"""Ingest stage: read a dataset folder into a manifest of usable images and a quarantine table.

Three layouts are read (``dataset.source`` in params.yaml):

* ``generic``: ``<class>/<visual|tactile>/<name>.<ext>``; a visual and a tactile image with the
  same name are one view of one sample (``pair_key`` = name).
* ``synthetic``: the generic layout written by :mod:`vtgen.synthetic`, plus its ``dataset.json``.
* ``vitac``: ``<cloth>t/``, ``<cloth>v/``, ``<cloth>t_test/``, ``<cloth>v_test/`` folders of JPEGs;
  tactile files ``<frame>_<tile>.jpg`` (source = GelSight frame), visual files
  ``IMG_<photo>_<tile>.jpg`` (source = photo). Modalities are not aligned; ``_test`` is the test split.

Every file found ends up either in the manifest (possibly converted, with a note) or in the
quarantine table with its reason; the counts in, kept and quarantined are printed and recorded.
Names that are not valid UTF-8 cannot be stored in the tables, so such files and folders are
quarantined (shown with ``\\xff`` escapes) rather than read. Symbolic links to files are read
through; symbolic links to folders inside a modality folder are quarantined, not followed, since
one can loop back to its own parent.

Memory: the readers list file names only; decoding runs on ``ingest.workers`` threads, one image
per thread at a time, with at most a few images per worker in flight (:func:`vtgen.imageio.stream_map`); each
decoded image is reduced at once to its metadata, appended column by column to the manifest, so
memory grows by a few hundred bytes of metadata per file, never with the pixels.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from vtgen.io.images import atomic_output_dir, check_output_dir, display_path, file_md5, IMAGE_EXTENSIONS, ImageError, is_utf8_path, read_rgb8, stream_map
from vtgen.io.tables import MANIFEST_COLUMNS, QUARANTINE_COLUMNS

MODALITIES = ("visual", "tactile")
_VITAC_FOLDER = re.compile(r"^(?P<cloth>\d+)(?P<mod>[tv])(?P<test>_test)?$")
_VITAC_TACTILE = re.compile(r"^(?P<frame>\d+)_(?P<tile>\d+)$")
_VITAC_VISUAL = re.compile(r"^IMG_(?P<photo>\d+)_(?P<tile>\d+)$")


class IngestError(RuntimeError):
    """Nothing usable is left in the dataset; the message says what was found."""


@dataclass(slots=True)
class Candidate:
    """A file a reader found, with what its place in the layout says about it."""

    path: str
    cls: str
    modality: str
    split: str = ""          # "test" or "train" when the dataset fixes it, "" when pairing decides
    source: str = ""         # the physical capture the image came from (the unit of splitting)
    pair_key: str = ""       # equal keys across modalities mark an aligned view; "" for none
    note: str = ""


_NOT_UTF8 = "name is not valid UTF-8 text, so it cannot be recorded; rename it to use it"
_LINKED_FOLDER = "symbolic link to a folder: not followed (it could loop); link the files or copy the folder instead"


def _quarantine(path, cls, modality, reason) -> dict:
    return {"path": display_path(path), "class": display_path(cls), "modality": modality, "reason": reason}


def _is_image_name(path: Path) -> bool:
    return path.suffix.lower() in IMAGE_EXTENSIONS


def _files_below(folder: Path, cls: str, modality: str, quarantined: list[dict]) -> list[Path]:
    """Files below ``folder`` in sorted order. Folders reached through a symbolic link and
    names that are not UTF-8 go to ``quarantined`` instead (pathlib's rglob does not descend
    into linked folders, so a link loop cannot trap the walk)."""
    files = []
    for path in sorted(folder.rglob("*")):
        if path.is_symlink() and path.is_dir():
            quarantined.append(_quarantine(path, cls, modality, _LINKED_FOLDER))
        elif path.is_dir():
            continue
        elif not is_utf8_path(path):
            quarantined.append(_quarantine(path, cls, modality, f"file {_NOT_UTF8}"))
        else:
            files.append(path)
    return files


def read_generic(root: Path) -> tuple[list[Candidate], list[dict]]:
    """Find images in the generic layout ``<class>/<visual|tactile>/<name>.<ext>``."""
    candidates, quarantined = [], []
    for class_dir in sorted(p for p in root.iterdir() if not p.name.startswith(".")):
        if not class_dir.is_dir():
            if _is_image_name(class_dir):
                quarantined.append(_quarantine(class_dir, "", "", "image at the top level; expected <class>/<modality>/ folders"))
            continue
        cls = class_dir.name
        if not is_utf8_path(cls):
            quarantined.append(_quarantine(class_dir, "", "", f"class folder {_NOT_UTF8}"))
            continue
        found_any = False
        for entry in sorted(class_dir.iterdir()):
            if entry.name not in MODALITIES:
                quarantined.append(_quarantine(entry, cls, "", f"not a modality folder (expected {' or '.join(MODALITIES)})"))
                continue
            if not entry.is_dir():
                quarantined.append(_quarantine(entry, cls, entry.name, "named like a modality folder but is not a folder"))
                continue
            for path in _files_below(entry, cls, entry.name, quarantined):
                if not _is_image_name(path):
                    quarantined.append(_quarantine(path, cls, entry.name, f"not an image file (extension '{path.suffix}')"))
                    continue
                found_any = True
                view = f"{cls}/{path.stem}"
                candidates.append(Candidate(str(path), cls, entry.name, source=view, pair_key=view))
        if not found_any:
            quarantined.append(_quarantine(class_dir, cls, "", "empty class: no image files"))
    return candidates, quarantined


def read_synthetic(root: Path) -> tuple[list[Candidate], list[dict]]:
    """Read the rendered synthetic dataset (generic layout plus ``dataset.json``)."""
    meta_path = root / "dataset.json"
    if not meta_path.is_file():
        raise IngestError(f"{root}: no dataset.json; is this a dataset written by `vtgen render`?")
    meta = json.loads(meta_path.read_text())
    if not meta.get("synthetic"):
        raise IngestError(f"{meta_path}: does not declare a synthetic dataset")
    return read_generic(root)


def read_vitac(root: Path) -> tuple[list[Candidate], list[dict]]:
    """Find images in the ViTac layout (``<cloth>t``, ``<cloth>v`` and their ``_test`` folders)."""
    candidates, quarantined = [], []
    for folder in sorted(p for p in root.iterdir() if not p.name.startswith(".")):
        match = _VITAC_FOLDER.match(folder.name)
        if not folder.is_dir() or not match:
            if folder.is_dir() or _is_image_name(folder):
                quarantined.append(_quarantine(folder, "", "", "not a ViTac folder (<cloth>t, <cloth>v, <cloth>t_test, <cloth>v_test)"))
            continue
        cls = match["cloth"]
        modality = "tactile" if match["mod"] == "t" else "visual"
        split = "test" if match["test"] else "train"
        files = _files_below(folder, cls, modality, quarantined)
        if not any(_is_image_name(p) for p in files):
            quarantined.append(_quarantine(folder, cls, modality, "empty folder: no image files"))
        for path in files:
            if not _is_image_name(path):
                quarantined.append(_quarantine(path, cls, modality, f"not an image file (extension '{path.suffix}')"))
                continue
            pattern = _VITAC_TACTILE if modality == "tactile" else _VITAC_VISUAL
            name = pattern.match(path.stem)
            if name is None:
                source, note = f"{cls}{match['mod']}:{path.stem}", "name does not follow ViTac naming; source is the file name"
            elif modality == "tactile":
                source, note = f"{cls}t:frame{name['frame']}", ""
            else:
                source, note = f"{cls}v:IMG_{name['photo']}", ""
            candidates.append(Candidate(str(path), cls, modality, split=split, source=source, note=note))
    return candidates, quarantined


READERS = {"generic": read_generic, "synthetic": read_synthetic, "vitac": read_vitac}


def _inspect(candidate: Candidate) -> dict:
    """Decode one candidate fully; return a manifest row or a quarantine row (key 'reason')."""
    try:
        image = read_rgb8(candidate.path)
        md5 = file_md5(candidate.path)
    except ImageError as exc:
        return _quarantine(candidate.path, candidate.cls, candidate.modality, str(exc))
    except OSError as exc:  # gone or unreadable between decoding and hashing
        return _quarantine(candidate.path, candidate.cls, candidate.modality, f"cannot read file: {exc.strerror or exc}")
    return {
        "path": candidate.path, "md5": md5, "modality": candidate.modality, "class": candidate.cls,
        "split": candidate.split, "source": candidate.source, "group": candidate.source, "pair_key": candidate.pair_key,
        "width": image.rgb.shape[1], "height": image.rgb.shape[0], "channels": image.channels,
        "bit_depth": image.bit_depth, "note": "; ".join(n for n in (candidate.note, image.note) if n),
    }


def ingest_dataset(root: str | Path, source: str, workers: int = 2, progress: bool = True) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """Read the dataset at ``root`` with the ``source`` reader.

    Returns (manifest, quarantine, summary). Raises IngestError naming the folder when the
    folder is missing or nothing usable is left after quarantine.
    """
    root = Path(root)
    if source not in READERS:
        raise IngestError(f"unknown dataset source '{source}' (known: {', '.join(READERS)})")
    if not root.is_dir():
        raise IngestError(f"{display_path(root)}: dataset folder does not exist")
    if not is_utf8_path(root.resolve()):
        raise IngestError(f"{display_path(root.resolve())}: the dataset folder's path is not valid UTF-8 text, "
                          f"so its files cannot be recorded; rename it")
    started = time.perf_counter()
    candidates, quarantined = READERS[source](root)
    entries_in = len(candidates) + len(quarantined)
    decoded = len(candidates)
    # The manifest is built column by column from one small row per image; the pixels of an
    # image are dropped as soon as _inspect returns.
    columns: dict[str, list] = {name: [] for name in MANIFEST_COLUMNS}
    for result in stream_map(_inspect, candidates, workers, decoded, "ingest", progress):
        if "reason" in result:
            quarantined.append(result)
        else:
            for name, values in columns.items():
                values.append(result[name])
    del candidates
    manifest = pd.DataFrame(columns, columns=MANIFEST_COLUMNS)
    del columns
    # A class needs both modalities to be paired in either direction.
    for cls, group in manifest.groupby("class"):
        present = set(group["modality"])
        if present != set(MODALITIES):
            missing = (set(MODALITIES) - present).pop()
            reason = f"class '{cls}' has no usable {missing} images, so it cannot be paired"
            quarantined.extend(_quarantine(p, cls, m, reason) for p, m in zip(group["path"], group["modality"]))
            manifest = manifest[manifest["class"] != cls]
    manifest = manifest.sort_values(["class", "modality", "path"]).reset_index(drop=True)
    quarantine = pd.DataFrame(quarantined, columns=QUARANTINE_COLUMNS)
    seconds = time.perf_counter() - started
    summary = {
        "root": str(root),
        "source": source,
        "synthetic": source == "synthetic",
        "entries_in": entries_in,  # image files found plus entries the layout rejected; = kept + quarantined
        # documentation and metadata beside the class folders (e.g. SOURCE.md, dataset.json) are not data
        "ignored_top_level_files": sorted(display_path(p.name) for p in root.iterdir() if not p.is_dir() and not _is_image_name(p)),
        "images_decoded": decoded,
        "kept": len(manifest),
        "with_note": int((manifest["note"] != "").sum()),
        "quarantined": len(quarantine),
        "classes": sorted(manifest["class"].unique().tolist()),
        "per_class_modality": {f"{c}/{m}": int(n) for (c, m), n in manifest.groupby(["class", "modality"]).size().items()},
        "seconds": round(seconds, 3),
        "images_per_second": round(decoded / seconds, 1) if seconds > 0 else None,
    }
    if manifest.empty:
        reasons = quarantine["reason"].value_counts().head(5).to_dict()
        raise IngestError(
            f"{root}: no usable images left ({decoded} image files decoded, {len(quarantine)} quarantined; "
            f"most common reasons: {reasons})"
        )
    return manifest, quarantine, summary


def run_ingest(root: str | Path, source: str, out_dir: str | Path, workers: int = 2) -> dict:
    """Stage entry: write manifest.parquet, quarantine.parquet/.csv and summary.json into ``out_dir``."""
    check_output_dir(out_dir)  # before decoding the whole dataset, not after
    manifest, quarantine, summary = ingest_dataset(root, source, workers)
    with atomic_output_dir(out_dir) as tmp:
        manifest.to_parquet(tmp / "manifest.parquet", index=False)
        quarantine.to_parquet(tmp / "quarantine.parquet", index=False)
        quarantine.to_csv(tmp / "quarantine.csv", index=False)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(
        f"ingest: {summary['images_decoded']} image files in, {summary['kept']} kept "
        f"({summary['with_note']} with a conversion note), {summary['quarantined']} quarantined entries; "
        f"{summary['images_per_second']} images/s"
    )
    if summary["ignored_top_level_files"]:
        print(f"  not data, ignored: {', '.join(summary['ignored_top_level_files'])}")
    for reason, count in quarantine["reason"].value_counts().items():
        print(f"  quarantined x{count}: {reason}")
    notes = manifest.loc[manifest["note"] != "", "note"]
    for note, count in notes.value_counts().items():
        print(f"  warning: kept x{count} with conversion: {note}")
    return summary
