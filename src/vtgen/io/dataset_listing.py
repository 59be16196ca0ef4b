"""Listing a dataset folder: the files a layout accepts as Candidates, and a quarantine row for the rest.

:func:`read_layout` walks the folder (following symbolic links inside it, quarantining loops, links
leading outside and names that are not UTF-8 or hold control characters) and matches every file to
the :class:`~vtgen.io.layouts.Layout`; :func:`read_user_manifest` reads the table a user wrote
(``source: manifest``) instead. Both return (candidates, quarantine rows, ignored top-level files).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pandas as pd

from vtgen.io.images import display_path, IMAGE_EXTENSIONS, is_utf8_path
from vtgen.io.layouts import Candidate, folder_problem, interpret, KNOWN_FIELDS, Layout, match_file, modality_rules

_NOT_UTF8 = "name is not valid UTF-8 text, so it cannot be recorded; rename it to use it"
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_CONTROL_NAME = ("name contains a control character (a line break, tab or other), which would reach tile file names "
                 "and tables; rename it to use it")


def _inside(path: str | Path, root_real: str) -> bool:
    """Whether ``path``, links resolved, lies inside the folder whose resolved path is ``root_real``."""
    return os.path.commonpath([os.path.realpath(path), root_real]) == root_real


def _outside_reason(path: str | Path, what: str) -> str:
    return (f"{what} outside dataset.path (it resolves to {display_path(os.path.realpath(path))}): not read; every "
            f"image a run reads must lie inside dataset.path, so that a change to it reruns the run")


def quarantine_row(path, cls, modality, reason) -> dict:
    """A row of the quarantine table: the file, its class and modality as far as known, and why it is not used."""
    return {"path": display_path(path), "class": display_path(cls), "modality": modality, "reason": reason}


def is_image_name(path: str | Path) -> bool:
    """Whether the name has an image extension (any case)."""
    return Path(path).suffix.lower() in IMAGE_EXTENSIONS


def _walk(root: Path, quarantined: list[dict]) -> tuple[list[str], list[str], list[str]]:
    """(files, empty folders, top-level non-folder entries) below ``root``, relative, sorted.

    Symbolic links to folders are followed unless they lead back to a folder already being read
    (a loop), which is quarantined; links that resolve outside ``root`` and names that are not UTF-8 or
    hold control characters are quarantined."""
    files, empty, top = [], [], []
    root_real = os.path.realpath(root)
    seen = {root_real}

    def visit(folder: Path, rel: str, ancestors: frozenset) -> bool:
        try:
            entries = sorted(os.scandir(folder), key=lambda e: e.name)
        except OSError as exc:
            quarantined.append(quarantine_row(folder, "", "", f"cannot list folder: {exc.strerror or exc}"))
            return True
        found = False
        for entry in entries:
            name_rel = f"{rel}/{entry.name}" if rel else entry.name
            if not rel and entry.name.startswith("."):
                continue  # .dvc, .git and other hidden top-level entries are not data
            if not is_utf8_path(entry.name) or _CONTROL.search(entry.name):
                what = "folder" if entry.is_dir() else "file"
                problem = _NOT_UTF8 if not is_utf8_path(entry.name) else _CONTROL_NAME
                quarantined.append(quarantine_row(entry.path, "", "", f"{what} {problem}"))
                found = True
                continue
            try:
                is_dir = entry.is_dir()
            except OSError:
                is_dir = False
            if entry.is_symlink() and not _inside(entry.path, root_real):
                what = "symbolic link to a folder" if is_dir else "symbolic link to a file"
                quarantined.append(quarantine_row(entry.path, "", "", _outside_reason(entry.path, what)))
                found = True
                continue
            if is_dir:
                real = os.path.realpath(entry.path)
                if entry.is_symlink() and (real in ancestors or real in seen):
                    quarantined.append(quarantine_row(entry.path, "", "", "symbolic link to a folder that is already "
                                                      "read (it loops back or repeats it): not followed"))
                    found = True
                    continue
                seen.add(real)
                if not visit(Path(entry.path), name_rel, ancestors | {real}):
                    empty.append(name_rel)
                found = True
            elif not rel and not is_image_name(entry.name):
                top.append(entry.name)
            else:
                files.append(name_rel)
                found = True
        return found

    visit(root, "", frozenset({os.path.realpath(root)}))
    return files, empty, top


def read_layout(root: Path, layout: Layout) -> tuple[list[Candidate], list[dict], list[str]]:
    """Candidates, quarantine rows and ignored top-level files of the dataset at ``root``."""
    quarantined: list[dict] = []
    files, empty, top = _walk(root, quarantined)
    candidates = []
    pruned: set[str] = set()
    for rel in files:
        parts = rel.split("/")
        path = str(root / rel)
        if any("/".join(parts[:k]) in pruned for k in range(1, len(parts))):
            continue
        result = match_file(rel, layout, path)
        if isinstance(result, Candidate):
            if not is_image_name(rel):
                quarantined.append(quarantine_row(path, result.cls, result.modality,
                                                  f"not an image file (extension '{Path(rel).suffix}')"))
            else:
                candidates.append(result)
            continue
        cls, modality, reason = result
        bad_folder = folder_problem(parts[:-1], layout) if len(parts) > 1 else ""
        if bad_folder:  # one row for the whole folder, not one per file in it
            for k in range(1, len(parts)):
                if folder_problem(parts[:k], layout):
                    pruned.add("/".join(parts[:k]))
                    quarantined.append(quarantine_row(root / "/".join(parts[:k]), "", "",
                                                      folder_problem(parts[:k], layout)))
                    break
            continue
        quarantined.append(quarantine_row(path, cls, modality, reason))
    for rel in empty:
        parts = rel.split("/")
        if any("/".join(parts[:k]) in pruned for k in range(1, len(parts) + 1)):
            continue
        problem = folder_problem(parts, layout)
        if not problem:
            first = layout.patterns[0].segments
            is_class = len(parts) <= len(first) and first[len(parts) - 1].fields == ["class"]
            problem = "empty class: no image files" if is_class else "empty folder: no image files"
        quarantined.append(quarantine_row(root / rel, "", "", problem))
    return candidates, quarantined, top


def read_user_manifest(root: Path, dataset: dict) -> tuple[list[Candidate], list[dict], list[str]]:
    """Candidates from a CSV/parquet table (``dataset.manifest``, relative to ``root``) the user wrote."""
    name = dataset.get("manifest") or ""
    if not name:
        raise ValueError("dataset.manifest: required when dataset.source is 'manifest' (a CSV or parquet file "
                         "inside dataset.path with columns path, modality, class)")
    table_path = root / name
    if not table_path.is_file():
        raise ValueError(f"dataset.manifest: {display_path(table_path)} does not exist")
    try:
        table = (pd.read_parquet(table_path) if table_path.suffix.lower() in (".parquet", ".pq")
                 else pd.read_csv(table_path, dtype=str, keep_default_na=False))
    except Exception as exc:  # noqa: BLE001 - any parser failure is the file's fault
        raise ValueError(f"dataset.manifest: {display_path(table_path)} is not a readable CSV/parquet table: {exc}") from exc
    layout = Layout([], *modality_rules(dataset))
    needed = ["path", "class"] + ([] if layout.modality else ["modality"])
    missing = [c for c in needed if c not in table.columns]
    if missing:
        raise ValueError(f"dataset.manifest: {display_path(table_path)} lacks column(s) {', '.join(missing)} "
                         f"(columns: path, modality, class, and optionally {', '.join(KNOWN_FIELDS[2:])})")
    optional = [c for c in KNOWN_FIELDS if c in table.columns]
    candidates, quarantined, listed = [], [], set()
    root_real = os.path.realpath(root)
    csv = table_path.suffix.lower() not in (".parquet", ".pq")
    for number, row in enumerate(table.astype(str).to_dict("records")):
        rel = row["path"].strip()
        path = Path(rel) if os.path.isabs(rel) else root / rel
        listed.add(os.path.normpath(path))
        values = {c: row[c].strip() for c in optional if row[c].strip() not in ("", "nan", "None")}
        where = f"{name} {'line' if csv else 'row'} {number + 2 if csv else number + 1}"
        if not _inside(path, root_real):
            quarantined.append(quarantine_row(path, values.get("class", ""), values.get("modality", ""),
                                              f"{where}: " + _outside_reason(path, "path")))
            continue
        if _CONTROL.search(rel) or any(_CONTROL.search(v) for v in values.values()):
            quarantined.append(quarantine_row(path, values.get("class", ""), values.get("modality", ""),
                                              f"{where}: {_CONTROL_NAME.replace('name', 'the row', 1)}"))
            continue
        result = interpret(values, layout, rel, {}, "", str(path))
        if isinstance(result, str):
            quarantined.append(quarantine_row(path, values.get("class", ""), values.get("modality", ""), result))
        elif not is_image_name(path):
            quarantined.append(quarantine_row(path, result.cls, result.modality,
                                              f"not an image file (extension '{path.suffix}')"))
        else:
            candidates.append(result)
    walked: list[dict] = []
    files, _, top = _walk(root, walked)
    known = {row["path"] for row in quarantined}
    quarantined += [row for row in walked if row["path"] not in known]  # a listed link outside: one row, not two
    for rel in files:
        if os.path.normpath(root / rel) not in listed and is_image_name(rel):
            quarantined.append(quarantine_row(root / rel, "", "", f"image not listed in the manifest {name}"))
    top = [t for t in top if t != name]
    return candidates, quarantined, top

