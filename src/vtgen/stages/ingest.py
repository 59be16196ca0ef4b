"""Ingest stage: read a dataset folder into a manifest of usable images and a quarantine table.

A dataset is *described*, not forced into one layout (``dataset`` in params.yaml, see docs/data.md):

* ``source: pattern``: ``dataset.pattern`` is a path pattern relative to ``dataset.path`` with named
  fields, e.g. ``{modality}/{class}/{instance}/{name}.jpg``. Fields ``class`` and ``modality`` are
  required (or a fixed ``dataset.modality`` for a one-modality folder); ``split``, ``pair``,
  ``instance``, ``session`` and ``source`` are optional; any other name (``name``, ``frame``,
  ``ext``...) is captured and may be used in templates. A field matches one path part by default;
  ``{field:regex}`` or ``dataset.fields`` give it a regular expression. The pattern may be a list,
  tried in order; an entry may be a mapping with the pattern and templates for ``source``, ``pair``,
  ``instance`` or ``session`` built from the captured fields, and a ``note`` for the images it matches.
* ``source: manifest``: a CSV or parquet table the user writes (``dataset.manifest``, inside
  ``dataset.path``) with columns ``path``, ``modality``, ``class`` and any of the optional fields.
* ``generic``, ``synthetic`` and ``vitac`` are named presets of the pattern mechanism
  (:data:`vtgen.io.layouts.PRESETS`); ``synthetic`` also requires the renderer's ``dataset.json``.

Modality names are matched case-insensitively through :data:`MODALITY_ALIASES`, extended by
``dataset.modality_aliases``. Every file found ends up in the manifest (possibly converted, with a
note) or in the quarantine table with its reason; top-level files that are not images (README,
dataset.json) are listed as ignored. Folders reached through a symbolic link are read unless the
link leads back to a folder already being read (a loop), which is quarantined.

Splitting groups (``group``): the coarsest grouping the data gives, within a class: the instance,
else the session, else the source; images sharing a pair key are joined. Then exact duplicates
(same MD5) and near-duplicates (16 x 16 greyscale thumbnails within ``near_duplicates.rms`` grey
levels RMS and ``near_duplicates.relative`` of their contrast; see :func:`vtgen.core.grouping.near_duplicate_blocks`) of
one class are merged into one group with union-find; duplicates across classes are warned about.

A class with one modality only is kept; the summary says which modalities exist and whether
translation is possible. A failed ingest (nothing usable) still writes its quarantine table and a
``status: failed`` summary, without a manifest, and then raises.

Where each part lives: the description and its path patterns in :mod:`vtgen.io.layouts`, the
folder walk and the user's manifest table in :mod:`vtgen.io.dataset_listing`, decoding in
:mod:`vtgen.io.decoding`, union-find and duplicate detection in :mod:`vtgen.core.grouping`; this
module runs them in order, words the duplicate warnings and writes the stage's files.

Memory and speed: names are listed first; decoding runs on ``ingest.workers`` threads with a
bounded window (:func:`vtgen.io.images.stream_map`); each image is reduced at once to a row of
metadata and a 256-byte thumbnail. 8-bit greyscale and RGB files whose content matches their
extension are decoded once with Pillow without the RGB expansion (the conversion note is the one
:func:`vtgen.io.images.read_rgb8` would give); every other file goes through ``read_rgb8``.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from vtgen.core.domain import MODALITIES
from vtgen.core.grouping import (
    group_names, merge_exact_duplicates, merge_near_duplicates, THUMB, UnionFind, union_equal,
)
from vtgen.io.timing import write_timing
from vtgen.io.dataset_listing import read_layout, read_user_manifest
from vtgen.io.decoding import inspect_candidate
from vtgen.io.images import atomic_output_dir, check_output_dir, display_path, is_utf8_path, stream_map
from vtgen.io.layouts import Candidate, compile_layout, SOURCES
from vtgen.io.tables import MANIFEST_COLUMNS, QUARANTINE_COLUMNS

DEFAULT_NEAR_DUPLICATES = {"rms": 1.5, "relative": 0.05}
WARNED_PAIRS = 5  # duplicates across classes named one by one in the warnings (of each kind); the rest are counted


class IngestError(RuntimeError):
    """The dataset cannot be read, or nothing usable is left; the message says what was found.

    ``quarantine`` and ``summary`` hold what was recorded before the failure (None when the
    description itself was wrong)."""

    def __init__(self, message: str, quarantine: pd.DataFrame | None = None, summary: dict | None = None):
        super().__init__(message)
        self.quarantine, self.summary = quarantine, summary


# --- groups -------------------------------------------------------------------------------------


def _starting_keys(manifest: pd.DataFrame) -> list[str]:
    """Each row's coarsest grouping within its class: the instance, else the session, else the source."""
    cls = manifest["class"].to_numpy()
    return [f"{c}/{i}" if i else f"{c}/{s}" if s else src
            for c, i, s, src in zip(cls, manifest["instance"], manifest["session"], manifest["source"])]


def _duplicate_warnings(manifest: pd.DataFrame, exact: list[tuple[int, int]], near: list[tuple[str, int, int]],
                        cross_exact: int, cross_near: int) -> list[str]:
    """The warnings about duplicates across classes: the example pairs by name, then the totals."""
    path_of, cls = manifest["path"], manifest["class"].to_numpy()

    def name(i: int) -> str:
        return f"{display_path(path_of.iat[i])} ({cls[i]})"

    warnings = [f"identical files in different classes (label noise?): {name(j)} and {name(i)}" for j, i in exact]
    warnings += [f"near-duplicate {modality} images in different classes (label noise?): {name(i)} and {name(j)}"
                 for modality, i, j in near]
    if cross_exact > WARNED_PAIRS or cross_near > WARNED_PAIRS:
        warnings.append(f"in all: {cross_exact} file(s) identical to a file of another class and {cross_near} "
                        f"near-duplicate pair(s) across classes; they are not merged (a group never spans classes)")
    return warnings


def assign_groups(manifest: pd.DataFrame, thumbs: np.ndarray, rms: float, relative: float) -> tuple[list[str], dict, list[str]]:
    """Split group of every manifest row, duplicate counts and warnings.

    The group starts as the coarsest grouping the data gives within a class (instance, else session,
    else source), joins images sharing a pair key, then merges exact (MD5) and near-duplicates
    (:func:`vtgen.core.grouping.near_duplicate_blocks`, same modality) of one class. A group is named
    after its smallest starting key. Duplicates across classes are counted and warned about, never merged."""
    n = len(manifest)
    if n == 0:
        return [], {"exact_duplicate_files": 0, "near_duplicate_files": 0, "groups_before_merging": 0,
                    "groups_after_merging": 0, "files_identical_to_another_class": 0,
                    "near_duplicate_pairs_across_classes": 0}, []
    cls_codes, _ = pd.factorize(manifest["class"])
    md5_codes, _ = pd.factorize(manifest["md5"])
    keys = _starting_keys(manifest)
    uf = UnionFind(n)
    class_key = pd.Series(cls_codes).astype(str) + "\0"
    union_equal(uf, pd.factorize(class_key + pd.Series(keys))[0])
    pairs = manifest["pair_key"].reset_index(drop=True)
    union_equal(uf, np.where(pairs != "", pd.factorize(class_key + pairs)[0], -1))
    del class_key, pairs
    groups_before = len(np.unique(uf.roots()))
    exact, cross_exact, exact_pairs = merge_exact_duplicates(uf, md5_codes, cls_codes, WARNED_PAIRS)
    # near-duplicates, per modality: merged within a class, counted across classes
    near, cross_near, near_pairs = merge_near_duplicates(uf, thumbs, manifest.groupby("modality").indices, cls_codes,
                                                         md5_codes, rms, relative, WARNED_PAIRS)
    warnings = _duplicate_warnings(manifest, exact_pairs, near_pairs, cross_exact, cross_near)
    names, groups_after = group_names(uf, keys)
    counts = {"exact_duplicate_files": int(exact.sum()), "near_duplicate_files": int((near & ~exact).sum()),
              "groups_before_merging": groups_before, "groups_after_merging": groups_after,
              "files_identical_to_another_class": cross_exact, "near_duplicate_pairs_across_classes": cross_near,
              "near_duplicate_rule": f"{THUMB}x{THUMB} greyscale thumbnails within {rms} grey levels RMS and "
                                     f"{relative} of their contrast, same class and modality"}
    return names, counts, warnings


# --- the stage ----------------------------------------------------------------------------------


def _dataset_spec(dataset: str | dict) -> dict:
    spec = {"source": dataset} if isinstance(dataset, str) else dict(dataset)
    source = spec.get("source")
    if source not in SOURCES:
        raise IngestError(f"unknown dataset source '{source}' (known: {', '.join(SOURCES)})")
    return spec


def _translation(manifest: pd.DataFrame) -> dict:
    present = sorted(set(manifest["modality"]))
    if set(present) == set(MODALITIES):
        both = manifest.groupby("class")["modality"].nunique()
        one = sorted(both.index[both < 2])
        reason = "" if not one else f"classes with one modality only (not translated): {', '.join(map(str, one))}"
        return {"possible": True, "reason": reason}
    if not present:
        return {"possible": False, "reason": "no usable images"}
    missing = (set(MODALITIES) - set(present)).pop()
    return {"possible": False, "reason": f"the data has no usable {missing} images (only {present[0]}), so there is "
                                         f"nothing to translate from or to; splits and classification still work"}


def _check_root(root: Path) -> None:
    """IngestError unless ``root`` is a folder whose path can be recorded as text."""
    if not root.is_dir():
        raise IngestError(f"{display_path(root)}: dataset folder does not exist")
    if not is_utf8_path(root.resolve()):
        raise IngestError(f"{display_path(root.resolve())}: the dataset folder's path is not valid UTF-8 text, "
                          f"so its files cannot be recorded; rename it")


def _list_candidates(root: Path, spec: dict) -> tuple[list[Candidate], list[dict], list[str], str]:
    """(candidates, quarantine rows, ignored top-level files, the layout as text) of the dataset at
    ``root``; IngestError when the description is wrong."""
    source = spec["source"]
    try:
        if source == "synthetic":
            meta_path = root / "dataset.json"
            if not meta_path.is_file():
                raise IngestError(f"{root}: no dataset.json; is this a dataset written by `vtgen render`?")
            if not json.loads(meta_path.read_text()).get("synthetic"):
                raise IngestError(f"{meta_path}: does not declare a synthetic dataset")
        if source == "manifest":
            candidates, quarantined, top = read_user_manifest(root, spec)
            layout_text = f"manifest {spec['manifest']}"
        else:
            layout = compile_layout(spec)
            candidates, quarantined, top = read_layout(root, layout)
            layout_text = layout.text
    except ValueError as exc:
        raise IngestError(str(exc)) from exc
    return candidates, quarantined, top, layout_text


def _decode_all(candidates: list[Candidate], quarantined: list[dict], workers: int, progress: bool
                ) -> tuple[pd.DataFrame, np.ndarray]:
    """Decode every candidate on ``workers`` threads: (manifest rows, ungrouped, with instance and
    session; their thumbnails). Files that cannot be used are appended to ``quarantined``."""
    decoded = len(candidates)
    columns: dict[str, list] = {name: [] for name in [*MANIFEST_COLUMNS, "instance", "session"]}
    thumbs = np.empty((decoded, THUMB, THUMB), dtype=np.uint8)
    kept = 0
    # our workers are the parallelism: OpenCV's own thread pool (thumbnails) on top of them only adds contention
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if workers > 1 else opencv_threads)
    try:
        for result in stream_map(inspect_candidate, candidates, workers, decoded, "ingest", progress):
            if "reason" in result:
                quarantined.append(result)
                continue
            thumbs[kept] = result.pop("thumb")
            kept += 1
            for name, values in columns.items():
                values.append(result[name])
    finally:
        cv2.setNumThreads(opencv_threads)
    return pd.DataFrame(columns), thumbs[:kept]


def ingest_dataset(root: str | Path, dataset: str | dict, workers: int = 2, progress: bool = True
                   ) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """Read the dataset at ``root`` as ``dataset`` describes it (a preset name or the params section).

    Returns (manifest, quarantine, summary). Raises IngestError naming the folder when the folder is
    missing, the description is wrong, or nothing usable is left (then with the quarantine and summary).
    """
    root = Path(root)
    spec = _dataset_spec(dataset)
    source = spec["source"]
    _check_root(root)
    near = {**DEFAULT_NEAR_DUPLICATES, **(spec.get("near_duplicates") or {})}
    started = time.perf_counter()
    candidates, quarantined, top, layout_text = _list_candidates(root, spec)
    entries_in = len(candidates) + len(quarantined)
    decoded = len(candidates)
    manifest, thumbs = _decode_all(candidates, quarantined, workers, progress)
    del candidates
    groups, duplicates, warnings = assign_groups(manifest, thumbs, near["rms"], near["relative"])
    manifest["group"] = groups
    manifest = manifest.sort_values(["class", "modality", "path"]).reset_index(drop=True)[MANIFEST_COLUMNS]
    quarantine = pd.DataFrame(quarantined, columns=QUARANTINE_COLUMNS)
    seconds = time.perf_counter() - started
    summary = {
        "status": "ok",
        "root": str(root),
        "source": source,
        "layout": layout_text,
        "synthetic": source == "synthetic",
        "entries_in": entries_in,  # image files found plus entries the layout rejected; = kept + quarantined
        # documentation and metadata beside the data (e.g. SOURCE.md, dataset.json) are not data
        "ignored_top_level_files": sorted(display_path(t) for t in top),
        "images_decoded": decoded,
        "kept": len(manifest),
        "with_note": int((manifest["note"] != "").sum()),
        "quarantined": len(quarantine),
        "classes": sorted(manifest["class"].unique().tolist()),
        "modalities": sorted(manifest["modality"].unique().tolist()),
        "translation": _translation(manifest),
        "per_class_modality": {f"{c}/{m}": int(n) for (c, m), n in manifest.groupby(["class", "modality"]).size().items()},
        "duplicates": duplicates,
        "groups_per_class": {str(c): int(n) for c, n in manifest.groupby("class")["group"].nunique().items()},
        "warnings": warnings,
        "seconds": round(seconds, 3),
        "images_per_second": round(decoded / seconds, 1) if seconds > 0 else None,
    }
    if manifest.empty:
        reasons = quarantine["reason"].value_counts().head(5).to_dict()
        summary["status"] = "failed"
        message = (f"{root}: no usable images left ({decoded} image files decoded, {len(quarantine)} quarantined; "
                   f"most common reasons: {reasons})")
        summary["error"] = message
        raise IngestError(message, quarantine, summary)
    return manifest, quarantine, summary


def _write_failure(out_dir: str | Path, root, source, exc: IngestError) -> None:
    quarantine = exc.quarantine if exc.quarantine is not None else pd.DataFrame(columns=QUARANTINE_COLUMNS)
    summary = exc.summary or {"status": "failed", "root": str(root), "source": source, "error": str(exc),
                              "entries_in": 0, "kept": 0, "quarantined": len(quarantine)}
    with atomic_output_dir(out_dir) as tmp:  # replaces any earlier output, manifest included
        quarantine.to_parquet(tmp / "quarantine.parquet", index=False)
        quarantine.to_csv(tmp / "quarantine.csv", index=False)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")


def run_ingest(root: str | Path, dataset: str | dict, out_dir: str | Path, workers: int = 2) -> dict:
    """Stage entry: write manifest.parquet, quarantine.parquet/.csv and summary.json into ``out_dir`` (its seconds
    and images per second into ``timing.json``, not the summary; the returned summary holds them).

    ``dataset`` is a preset name or the params ``dataset`` section. On failure the folder holds
    only the quarantine tables and a ``status: failed`` summary, and IngestError is raised."""
    check_output_dir(out_dir)  # before decoding the whole dataset, not after
    source = dataset if isinstance(dataset, str) else dataset.get("source")
    try:
        manifest, quarantine, summary = ingest_dataset(root, dataset, workers)
    except IngestError as exc:
        _write_failure(out_dir, root, source, exc)
        if exc.quarantine is not None:
            for reason, count in exc.quarantine["reason"].value_counts().items():
                print(f"  quarantined x{count}: {reason}")
            print(f"ingest: failed; quarantine table and summary written to {out_dir}")
        raise
    with atomic_output_dir(out_dir) as tmp:
        manifest.to_parquet(tmp / "manifest.parquet", index=False)
        quarantine.to_parquet(tmp / "quarantine.parquet", index=False)
        quarantine.to_csv(tmp / "quarantine.csv", index=False)
        times = ("seconds", "images_per_second")
        (tmp / "summary.json").write_text(json.dumps({k: v for k, v in summary.items() if k not in times}, indent=2) + "\n")
        # the reading and checking alone, apart from the command's wall time (its "seconds")
        write_timing(tmp, {"work_seconds": summary["seconds"], "images_per_second": summary["images_per_second"]})
    dup = summary["duplicates"]
    print(
        f"ingest: {summary['images_decoded']} image files in, {summary['kept']} kept "
        f"({summary['with_note']} with a conversion note), {summary['quarantined']} quarantined entries; "
        f"{summary['images_per_second']} images/s"
    )
    print(f"  modalities: {', '.join(summary['modalities'])}; translation "
          f"{'possible' if summary['translation']['possible'] else 'impossible'}"
          f"{': ' + summary['translation']['reason'] if summary['translation']['reason'] else ''}")
    print(f"  split groups: {dup['groups_before_merging']} before merging duplicates, {dup['groups_after_merging']} "
          f"after ({dup['exact_duplicate_files']} exact-duplicate files, {dup['near_duplicate_files']} near-duplicate "
          f"files)")
    if summary["ignored_top_level_files"]:
        print(f"  not data, ignored: {', '.join(summary['ignored_top_level_files'])}")
    for reason, count in quarantine["reason"].value_counts().items():
        print(f"  quarantined x{count}: {reason}")
    notes = manifest.loc[manifest["note"] != "", "note"]
    for note, count in notes.value_counts().items():
        print(f"  warning: kept x{count} with conversion: {note}")
    for warning in summary["warnings"]:
        print(f"  warning: {warning}")
    return summary
