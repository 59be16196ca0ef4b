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
  (:data:`PRESETS`); ``synthetic`` also requires the renderer's ``dataset.json``.

Modality names are matched case-insensitively through :data:`MODALITY_ALIASES`, extended by
``dataset.modality_aliases``. Every file found ends up in the manifest (possibly converted, with a
note) or in the quarantine table with its reason; top-level files that are not images (README,
dataset.json) are listed as ignored. Folders reached through a symbolic link are read unless the
link leads back to a folder already being read (a loop), which is quarantined.

Splitting groups (``group``): the coarsest grouping the data gives, within a class: the instance,
else the session, else the source; images sharing a pair key are joined. Then exact duplicates
(same MD5) and near-duplicates (16 x 16 greyscale thumbnails within ``near_duplicates.rms`` grey
levels RMS and ``near_duplicates.relative`` of their contrast; see :func:`near_duplicate_pairs`) of
one class are merged into one group with union-find; duplicates across classes are warned about.

A class with one modality only is kept; the summary says which modalities exist and whether
translation is possible. A failed ingest (nothing usable) still writes its quarantine table and a
``status: failed`` summary, without a manifest, and then raises.

Memory and speed: names are listed first; decoding runs on ``ingest.workers`` threads with a
bounded window (:func:`vtgen.io.images.stream_map`); each image is reduced at once to a row of
metadata and a 256-byte thumbnail. 8-bit greyscale and RGB files whose content matches their
extension are decoded once with Pillow without the RGB expansion (the conversion note is the one
:func:`vtgen.io.images.read_rgb8` would give); every other file goes through ``read_rgb8``.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from PIL import Image

from vtgen.io.images import (
    atomic_output_dir, check_output_dir, display_path, DECODED_FORMATS, IMAGE_EXTENSIONS, ImageError, is_utf8_path,
    MAX_PIXELS, read_rgb8, stream_map,
)
from vtgen.io.images import _FORMAT_OF_EXTENSION  # the format each extension promises, as read_rgb8 checks it
from vtgen.io.tables import MANIFEST_COLUMNS, QUARANTINE_COLUMNS

MODALITIES = ("visual", "tactile")
MODALITY_ALIASES = {
    "visual": "visual", "vision": "visual", "camera": "visual", "rgb": "visual", "v": "visual",
    "tactile": "tactile", "touch": "tactile", "gelsight": "tactile", "t": "tactile",
}
KNOWN_FIELDS = ("class", "modality", "split", "pair", "instance", "session", "source")
TEMPLATE_KEYS = ("source", "pair", "instance", "session")
SPLIT_NAMES = {"": "train", "train": "train", "training": "train", "val": "val", "valid": "val",
               "validation": "val", "dev": "val", "test": "test", "testing": "test"}
THUMB = 16  # side of the greyscale thumbnail compared for near-duplicates
DEFAULT_NEAR_DUPLICATES = {"rms": 1.5, "relative": 0.05}

PRESETS: dict[str, dict] = {
    # <class>/<visual|tactile>/[subfolders/]<name>.<ext>; one name in both modalities is one view
    "generic": {
        "pattern": [{"pattern": "{class}/{modality}/{subfolders}{name}.{ext}",
                     "source": "{class}/{name}", "pair": "{class}/{name}"}],
        "fields": {"subfolders": r"(?:[^/]+/)*", "ext": r"[^./]+"},
    },
    # ViTac: <cloth>t, <cloth>v, <cloth>t_test, <cloth>v_test; tactile <frame>_<tile>, visual IMG_<photo>_<tile>
    "vitac": {
        "pattern": [
            {"pattern": "{class}{modality:t}{split}/{frame}_{tile}.{ext}", "source": "{class}t:frame{frame}"},
            {"pattern": "{class}{modality:v}{split}/IMG_{photo}_{tile}.{ext}", "source": "{class}v:IMG_{photo}"},
            {"pattern": "{class}{modality:[tv]}{split}/{name}.{ext}", "source": "{class}{modality}:{name}",
             "note": "name does not follow ViTac naming; source is the file name"},
        ],
        "fields": {"class": r"\d+", "split": r"(?:_test)?", "frame": r"\d+", "photo": r"\d+", "tile": r"\d+",
                   "name": r"[^/]+", "ext": r"[^./]+"},
    },
}
PRESETS["synthetic"] = PRESETS["generic"]
SOURCES = (*PRESETS, "pattern", "manifest")


class IngestError(RuntimeError):
    """The dataset cannot be read, or nothing usable is left; the message says what was found.

    ``quarantine`` and ``summary`` hold what was recorded before the failure (None when the
    description itself was wrong)."""

    def __init__(self, message: str, quarantine: pd.DataFrame | None = None, summary: dict | None = None):
        super().__init__(message)
        self.quarantine, self.summary = quarantine, summary


@dataclass(slots=True)
class Candidate:
    """A file the layout accepted, with what its place in the layout says about it."""

    path: str
    cls: str
    modality: str
    split: str = ""          # "train", "val" or "test" when the dataset fixes it, "" when pairing decides
    source: str = ""         # the capture the image came from
    pair_key: str = ""       # equal keys across modalities mark one moment seen by both sensors; "" for none
    instance: str = ""       # the physical object or sample
    session: str = ""        # the recording session
    note: str = ""


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


def _quarantine(path, cls, modality, reason) -> dict:
    return {"path": display_path(path), "class": display_path(cls), "modality": modality, "reason": reason}


def _is_image_name(path: str | Path) -> bool:
    return Path(path).suffix.lower() in IMAGE_EXTENSIONS


# --- the dataset description --------------------------------------------------------------------


@dataclass
class _Segment:
    text: str
    regex: re.Pattern
    fields: list[str]


@dataclass
class _Pattern:
    text: str
    regex: re.Pattern
    segments: list[_Segment]
    templates: dict[str, str]
    note: str
    fields: set[str] = field(default_factory=set)


@dataclass
class Layout:
    """A compiled dataset description: patterns tried in order, modality aliases, a fixed modality."""

    patterns: list[_Pattern]
    aliases: dict[str, str]
    modality: str = ""

    @property
    def text(self) -> str:
        return " | ".join(p.text for p in self.patterns)


def _split_fields(text: str, key: str) -> list[tuple[str, str | None, str | None]]:
    """Parse a pattern into parts: ("lit", text, None) or ("field", name, regex or None).

    ``{{`` and ``}}`` are literal braces; a field's regex may hold braces of its own (``\\d{2}``)."""
    parts, i, literal = [], 0, ""
    while i < len(text):
        char = text[i]
        if text.startswith("{{", i) or text.startswith("}}", i):
            literal += char
            i += 2
            continue
        if char == "}":
            raise ValueError(f"{key}: unmatched '}}' at position {i} in '{text}' (write '}}}}' for a literal brace)")
        if char != "{":
            literal += char
            i += 1
            continue
        depth, j = 1, i + 1
        while j < len(text) and depth:
            depth += {"{": 1, "}": -1}.get(text[j], 0)
            j += 1
        if depth:
            raise ValueError(f"{key}: unclosed '{{' at position {i} in '{text}'")
        body = text[i + 1:j - 1]
        name, _, regex = body.partition(":")
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            raise ValueError(f"{key}: '{{{body}}}' is not a field (a field is {{name}} or {{name:regex}}, "
                             f"name made of letters, digits and _)")
        if literal:
            parts.append(("lit", literal, None))
            literal = ""
        parts.append(("field", name, regex if ":" in body else None))
        i = j
    if literal:
        parts.append(("lit", literal, None))
    return parts


def _field_regex(name: str, inline: str | None, fields: dict[str, str], key: str) -> str:
    regex = inline if inline is not None else fields.get(name, r"[^/]+")
    try:
        compiled = re.compile(regex)
    except re.error as exc:
        where = key if inline is not None else f"dataset.fields.{name}"
        raise ValueError(f"{where}: field '{name}' has an invalid regular expression '{regex}': {exc}") from exc
    if compiled.groupindex:
        raise ValueError(f"{key}: field '{name}': its regular expression may not hold named groups ((?P<...>))")
    return regex


def _compile_pattern(entry, fields: dict[str, str], fixed_modality: str, key: str) -> _Pattern:
    if isinstance(entry, str):
        entry = {"pattern": entry}
    if not isinstance(entry, dict) or not isinstance(entry.get("pattern"), str) or not entry["pattern"].strip():
        raise ValueError(f"{key}: expected a pattern text or a mapping with 'pattern', got {entry!r}")
    unknown = set(entry) - {"pattern", "note", *TEMPLATE_KEYS}
    if unknown:
        raise ValueError(f"{key}: unknown key(s) {', '.join(sorted(unknown))} (allowed: pattern, note, "
                         f"{', '.join(TEMPLATE_KEYS)})")
    text = entry["pattern"].strip()
    if text.startswith("/") or any(part in ("..", ".") for part in text.split("/")):
        raise ValueError(f"{key}: '{text}' must be relative to dataset.path, without '.', '..' or a leading '/'")
    parts = _split_fields(text, key)
    # split into path segments on '/' outside fields
    segments_parts: list[list] = [[]]
    for kind, value, regex in parts:
        if kind == "lit":
            pieces = value.split("/")
            for n, piece in enumerate(pieces):
                if n:
                    segments_parts.append([])
                if piece:
                    segments_parts[-1].append(("lit", piece, None))
        else:
            segments_parts[-1].append((kind, value, regex))
    if any(not seg for seg in segments_parts):
        raise ValueError(f"{key}: '{text}' has an empty path part ('//' or a trailing '/')")
    seen: set[str] = set()
    full, segments = [], []
    for seg in segments_parts:
        seg_regex, seg_fields, seg_seen = [], [], set()
        for kind, value, regex in seg:
            if kind == "lit":
                seg_regex.append(re.escape(value))
                full.append(re.escape(value))
                continue
            body = _field_regex(value, regex, fields, key)
            full.append(f"(?P={value})" if value in seen else f"(?P<{value}>{body})")
            seg_regex.append(f"(?P={value})" if value in seg_seen else f"(?P<{value}>{body})")
            seen.add(value)
            seg_seen.add(value)
            seg_fields.append(value)
        seg_text = "".join(v if k == "lit" else "{" + v + "}" for k, v, _ in seg)
        segments.append(_Segment(seg_text, re.compile("^" + "".join(seg_regex) + "$"), seg_fields))
        full.append("/")
    regex = re.compile("^" + "".join(full[:-1]) + "$")
    if "class" not in seen:
        raise ValueError(f"{key}: '{text}' has no {{class}} field; every image needs a class")
    if "modality" not in seen and not fixed_modality:
        raise ValueError(f"{key}: '{text}' has no {{modality}} field; add one or set dataset.modality "
                         f"(visual or tactile) for a one-modality folder")
    if "modality" in seen and fixed_modality:
        raise ValueError(f"{key}: '{text}' has a {{modality}} field and dataset.modality is set too; give one")
    templates = {}
    for name in TEMPLATE_KEYS:
        if name in entry:
            template = entry[name]
            if not isinstance(template, str):
                raise ValueError(f"{key}.{name}: expected a template text, got {template!r}")
            used = [v for k, v, _ in _split_fields(template, f"{key}.{name}") if k == "field"]
            missing = [u for u in used if u not in seen]
            if missing:
                raise ValueError(f"{key}.{name}: template '{template}' uses {', '.join(missing)}, "
                                 f"which the pattern '{text}' does not capture")
            if name in seen:
                raise ValueError(f"{key}.{name}: '{name}' is both a field of the pattern and a template; give one")
            templates[name] = template
    note = entry.get("note", "")
    if not isinstance(note, str):
        raise ValueError(f"{key}.note: expected text, got {note!r}")
    return _Pattern(text, regex, segments, templates, note, seen)


def _modality_rules(dataset: dict) -> tuple[dict[str, str], str]:
    """(alias -> modality, fixed modality or "") from ``dataset.modality_aliases`` and ``dataset.modality``."""
    aliases = dict(MODALITY_ALIASES)
    extra = dataset.get("modality_aliases") or {}
    for alias, modality in extra.items():
        if modality not in MODALITIES:
            raise ValueError(f"dataset.modality_aliases.{alias}: '{modality}' is not visual or tactile")
        aliases[str(alias).lower()] = modality
    fixed = dataset.get("modality") or ""
    if fixed:
        fixed = aliases.get(str(fixed).lower(), "")
        if not fixed:
            raise ValueError(f"dataset.modality: '{dataset['modality']}' is not a modality name "
                             f"(known: {', '.join(sorted(aliases))})")
    return aliases, fixed


def compile_layout(dataset: dict) -> Layout:
    """The :class:`Layout` a ``dataset`` params section (or preset) describes; ValueError naming the key."""
    source = dataset.get("source", "pattern")
    spec = dict(PRESETS[source]) if source in PRESETS else {}
    if source == "pattern":
        if not dataset.get("pattern"):
            raise ValueError("dataset.pattern: required when dataset.source is 'pattern' "
                             "(e.g. '{modality}/{class}/{instance}/{name}.jpg')")
        spec = {"pattern": dataset["pattern"], "fields": dataset.get("fields") or {}}
    fields = spec.get("fields") or {}
    if not isinstance(fields, dict) or not all(isinstance(v, str) for v in fields.values()):
        raise ValueError(f"dataset.fields: expected a mapping of field name to regular expression, got {fields!r}")
    aliases, fixed = _modality_rules(dataset)
    entries = spec["pattern"] if isinstance(spec.get("pattern"), list) else [spec.get("pattern")]
    if not entries:
        raise ValueError("dataset.pattern: the list of patterns is empty")
    key = "dataset.pattern"
    patterns = [_compile_pattern(e, fields, fixed, key if len(entries) == 1 else f"{key}[{i}]")
                for i, e in enumerate(entries)]
    return Layout(patterns, aliases, fixed)


@functools.lru_cache(maxsize=64)
def _template_parts(text: str) -> tuple:
    return tuple(_split_fields(text, "template"))


def _template(text: str, values: dict[str, str]) -> str:
    return "".join(v if k == "lit" else values.get(v, "") for k, v, _ in _template_parts(text))


def _split_value(raw: str) -> str | None:
    return SPLIT_NAMES.get(re.sub(r"[^a-z]", "", raw.lower()))


def _interpret(values: dict[str, str], layout: Layout, rel: str, templates: dict[str, str], note: str,
               path: str) -> Candidate | str:
    """A Candidate from the field values of one image, or the reason it cannot be used."""
    cls = values.get("class", "")
    if not cls:
        return "empty class name"
    if layout.modality:
        modality = layout.modality
    else:
        raw = values.get("modality", "")
        modality = layout.aliases.get(raw.lower(), "")
        if not modality:
            return (f"not a modality folder: '{raw}' names no modality (known: {', '.join(sorted(layout.aliases))}; "
                    f"add it to dataset.modality_aliases)")
    split = ""
    if "split" in values:
        split = _split_value(values["split"])
        if split is None:
            return f"unknown split '{values['split']}' (expected train, val or test, or empty)"
    derived = {name: _template(t, values) for name, t in templates.items()}
    get = lambda name: derived.get(name, values.get(name, ""))  # noqa: E731
    pair, instance, session, source = get("pair"), get("instance"), get("session"), get("source")
    if pair and "pair" not in templates:
        pair = f"{cls}/{pair}"
    if source and "source" not in templates:
        source = f"{cls}/{source}"
    if not source:
        source = pair or f"{cls}/{os.path.splitext(rel)[0]}"
    return Candidate(path, cls, modality, split, source, pair, instance, session, note)


def _match_file(rel: str, layout: Layout, path: str) -> Candidate | tuple[str, str, str]:
    """Match one file (path relative to the root) against the layout: a Candidate or (class, modality, reason)."""
    for pattern in layout.patterns:
        found = pattern.regex.match(rel)
        if found:
            values = {k: v for k, v in found.groupdict().items() if v is not None}
            result = _interpret(values, layout, rel, pattern.templates, pattern.note, path)
            if isinstance(result, str):
                return values.get("class", ""), layout.aliases.get(values.get("modality", "").lower(), ""), result
            return result
    parts = rel.split("/")
    first = layout.patterns[0]
    if len(parts) == 1 and len(first.segments) > 1:
        return "", "", f"image at the top level; the layout '{layout.text}' expects folders"
    problem = _folder_problem(parts[:-1], layout)
    if problem:
        return "", "", problem
    if len(parts) < len(first.segments):
        return "", "", f"is a file, not a folder; the layout '{layout.text}' expects a folder here"
    return "", "", f"does not match the layout '{layout.text}'"


def _folder_problem(parts: list[str], layout: Layout) -> str:
    """Why folders ``parts`` (relative to the root) cannot hold data of the layout, or ""."""
    reasons = []
    for pattern in layout.patterns:
        # only the leading segments that are folders (not the file-name segment) are checked
        checked = pattern.segments[:max(0, len(pattern.segments) - 1)]
        values: dict[str, str] = {}
        reason = ""
        for part, segment in zip(parts, checked):
            found = segment.regex.match(part)
            if not found:
                reason = f"folder '{part}' does not match '{segment.text}' of the layout '{layout.text}'"
                break
            values.update({k: v for k, v in found.groupdict().items() if v is not None})
        if not reason and "modality" in values and not layout.aliases.get(values["modality"].lower()):
            reason = (f"not a modality folder: '{values['modality']}' names no modality "
                      f"(known: {', '.join(sorted(layout.aliases))}; add it to dataset.modality_aliases)")
        if not reason and "split" in values and _split_value(values["split"]) is None:
            reason = f"unknown split '{values['split']}' (expected train, val or test, or empty)"
        if not reason:
            return ""
        reasons.append(reason)
    return reasons[0]


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
            quarantined.append(_quarantine(folder, "", "", f"cannot list folder: {exc.strerror or exc}"))
            return True
        found = False
        for entry in entries:
            name_rel = f"{rel}/{entry.name}" if rel else entry.name
            if not rel and entry.name.startswith("."):
                continue  # .dvc, .git and other hidden top-level entries are not data
            if not is_utf8_path(entry.name) or _CONTROL.search(entry.name):
                what = "folder" if entry.is_dir() else "file"
                problem = _NOT_UTF8 if not is_utf8_path(entry.name) else _CONTROL_NAME
                quarantined.append(_quarantine(entry.path, "", "", f"{what} {problem}"))
                found = True
                continue
            try:
                is_dir = entry.is_dir()
            except OSError:
                is_dir = False
            if entry.is_symlink() and not _inside(entry.path, root_real):
                what = "symbolic link to a folder" if is_dir else "symbolic link to a file"
                quarantined.append(_quarantine(entry.path, "", "", _outside_reason(entry.path, what)))
                found = True
                continue
            if is_dir:
                real = os.path.realpath(entry.path)
                if entry.is_symlink() and (real in ancestors or real in seen):
                    quarantined.append(_quarantine(entry.path, "", "", "symbolic link to a folder that is already "
                                                   "read (it loops back or repeats it): not followed"))
                    found = True
                    continue
                seen.add(real)
                if not visit(Path(entry.path), name_rel, ancestors | {real}):
                    empty.append(name_rel)
                found = True
            elif not rel and not _is_image_name(entry.name):
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
        result = _match_file(rel, layout, path)
        if isinstance(result, Candidate):
            if not _is_image_name(rel):
                quarantined.append(_quarantine(path, result.cls, result.modality,
                                               f"not an image file (extension '{Path(rel).suffix}')"))
            else:
                candidates.append(result)
            continue
        cls, modality, reason = result
        folder_problem = _folder_problem(parts[:-1], layout) if len(parts) > 1 else ""
        if folder_problem:  # one row for the whole folder, not one per file in it
            for k in range(1, len(parts)):
                if _folder_problem(parts[:k], layout):
                    pruned.add("/".join(parts[:k]))
                    quarantined.append(_quarantine(root / "/".join(parts[:k]), "", "", _folder_problem(parts[:k], layout)))
                    break
            continue
        quarantined.append(_quarantine(path, cls, modality, reason))
    for rel in empty:
        parts = rel.split("/")
        if any("/".join(parts[:k]) in pruned for k in range(1, len(parts) + 1)):
            continue
        problem = _folder_problem(parts, layout)
        if not problem:
            first = layout.patterns[0].segments
            is_class = len(parts) <= len(first) and first[len(parts) - 1].fields == ["class"]
            problem = "empty class: no image files" if is_class else "empty folder: no image files"
        quarantined.append(_quarantine(root / rel, "", "", problem))
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
    layout = Layout([], *_modality_rules(dataset))
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
            quarantined.append(_quarantine(path, values.get("class", ""), values.get("modality", ""),
                                           f"{where}: " + _outside_reason(path, "path")))
            continue
        if _CONTROL.search(rel) or any(_CONTROL.search(v) for v in values.values()):
            quarantined.append(_quarantine(path, values.get("class", ""), values.get("modality", ""),
                                           f"{where}: {_CONTROL_NAME.replace('name', 'the row', 1)}"))
            continue
        result = _interpret(values, layout, rel, {}, "", str(path))
        if isinstance(result, str):
            quarantined.append(_quarantine(path, values.get("class", ""), values.get("modality", ""), result))
        elif not _is_image_name(path):
            quarantined.append(_quarantine(path, result.cls, result.modality,
                                           f"not an image file (extension '{path.suffix}')"))
        else:
            candidates.append(result)
    walked: list[dict] = []
    files, _, top = _walk(root, walked)
    known = {row["path"] for row in quarantined}
    quarantined += [row for row in walked if row["path"] not in known]  # a listed link outside: one row, not two
    for rel in files:
        if os.path.normpath(root / rel) not in listed and _is_image_name(rel):
            quarantined.append(_quarantine(root / rel, "", "", f"image not listed in the manifest {name}"))
    top = [t for t in top if t != name]
    return candidates, quarantined, top


# --- decoding -----------------------------------------------------------------------------------


def _decode_fast(data: bytes, path: str) -> tuple[np.ndarray, str, int, int] | None:
    """(array, note, channels, bit depth) for an 8-bit L or RGB file whose format matches its
    extension, decoded once without expanding grey to RGB; None for anything else (read_rgb8 decides)."""
    expected = _FORMAT_OF_EXTENSION.get(Path(path).suffix.lower())
    try:
        with Image.open(io.BytesIO(data), formats=DECODED_FORMATS) as image:
            width, height = image.size
            if (image.mode not in ("L", "RGB") or image.format != expected or not 1 <= width * height <= MAX_PIXELS
                    or any(";16" in str(t.args) for t in getattr(image, "tile", []) if t.args)):
                return None
            mode = image.mode
            image.load()
            array = np.asarray(image)
    except Exception:  # noqa: BLE001 - read_rgb8 gives the reason
        return None
    if mode == "L":
        return array, "grayscale (L) replicated to RGB", 1, 8
    return array, "", 3, 8


def grey_thumbnail(array: np.ndarray) -> np.ndarray:
    """The THUMB x THUMB greyscale (area-averaged) thumbnail, uint8, of an (H, W) or (H, W, 3) image."""
    grey = array if array.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(array), cv2.COLOR_RGB2GRAY)
    height, width = grey.shape
    fy, fx = height // THUMB, width // THUMB
    if fx >= 3 and fy >= 3 and fx * THUMB == width and fy * THUMB == height and fx * fy <= 65536:
        # an integer shrink (640x480: 40 x 30 pixels per cell): OpenCV's INTER_AREA rounds each cell's
        # exact sum times float32(1 / cell area), half to even; the sums by cv2.reduce, 2-3x faster
        rows = cv2.reduce(np.ascontiguousarray(grey).reshape(height * THUMB, fx), 1, cv2.REDUCE_SUM, dtype=cv2.CV_32S)
        sums = rows.reshape(THUMB, fy, THUMB).sum(axis=1)
        return np.rint(sums.astype(np.float32) * np.float32(1.0 / (fx * fy))).astype(np.uint8)
    return cv2.resize(grey, (THUMB, THUMB), interpolation=cv2.INTER_AREA)


def _inspect(candidate: Candidate) -> dict:
    """Decode one candidate fully; a manifest row (plus its ``thumb``) or a quarantine row (key 'reason')."""
    try:
        with open(candidate.path, "rb") as handle:
            data = handle.read()
    except OSError:
        data = None  # read_rgb8 names the problem (loop, dangling link, permission)
    fast = _decode_fast(data, candidate.path) if data else None
    try:
        if fast is None:
            image = read_rgb8(candidate.path)
            fast = image.rgb, image.note, image.channels, image.bit_depth
            if data is None:
                raise OSError("file could not be read")
    except ImageError as exc:
        return _quarantine(candidate.path, candidate.cls, candidate.modality, str(exc))
    except OSError as exc:
        return _quarantine(candidate.path, candidate.cls, candidate.modality, f"cannot read file: {exc.strerror or exc}")
    array, note, channels, bit_depth = fast
    return {
        "path": candidate.path, "md5": hashlib.md5(data).hexdigest(), "modality": candidate.modality,
        "class": candidate.cls, "split": candidate.split, "source": candidate.source, "group": "",
        "pair_key": candidate.pair_key, "width": array.shape[1], "height": array.shape[0], "channels": channels,
        "bit_depth": bit_depth, "note": "; ".join(n for n in (candidate.note, note) if n),
        "instance": candidate.instance, "session": candidate.session, "thumb": grey_thumbnail(array),
    }


# --- groups -------------------------------------------------------------------------------------


class _UnionFind:
    def __init__(self, n: int):
        self.parent = np.arange(n)

    def find(self, i: int) -> int:
        parent = self.parent
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    def union(self, i: int, j: int) -> bool:
        a, b = self.find(i), self.find(j)
        if a == b:
            return False
        self.parent[max(a, b)] = min(a, b)
        return True


def _union_equal(uf: _UnionFind, codes: np.ndarray) -> None:
    """Join every index to the first index holding the same code (codes < 0 join nothing)."""
    codes = np.asarray(codes)
    _, first, inverse = np.unique(codes, return_index=True, return_inverse=True)
    for i, head in enumerate(first[inverse].tolist()):
        if codes[i] >= 0 and head != i:
            uf.union(head, i)


def near_duplicate_blocks(thumbs: np.ndarray, rms: float, relative: float, index=None, block: int = 32):
    """Yield ``(rows, cols, hits)``: index arrays into ``thumbs`` (restricted to ``index`` when given)
    and a boolean matrix marking the
    near-duplicate pairs among them (each unordered pair appears once, never an image with itself).

    Two images are near-duplicates when the RMS difference of their greyscale thumbnails is at most
    ``rms`` grey levels and at most ``relative`` times their contrast (the standard deviation of the
    thumbnails about their means, pooled). The second condition keeps apart the thumbnails of fine
    textures, which look flat at 16 px. Thumbnails are sorted by mean brightness and only blocks
    whose means lie within ``rms`` are compared (the RMS difference is at least the difference of
    the means); ``block`` x ``block`` pairs are compared at a time, so memory does not grow with
    the number of images.
    """
    index = np.arange(len(thumbs)) if index is None else np.asarray(index)
    n = len(index)
    if n < 2 or rms <= 0:
        return
    flat = thumbs.reshape(len(thumbs), -1)
    d = flat.shape[1]
    means, variances = np.empty(n, np.float32), np.empty(n, np.float32)
    for start in range(0, n, block):  # in blocks: a float copy of every thumbnail would be 1 KiB per image
        chunk = flat[index[start:start + block]].astype(np.float32)
        means[start:start + block], variances[start:start + block] = chunk.mean(axis=1), chunk.var(axis=1)
    del chunk
    order = np.argsort(means, kind="stable")
    index, means, variances = index[order], means[order], variances[order]
    norms = variances * d + means * means * d  # sum of squares of each thumbnail
    for start in range(0, n, block):
        stop = min(n, start + block)
        rows = flat[index[start:stop]].astype(np.float32)
        reach = int(np.searchsorted(means, means[stop - 1] + rms, side="right"))
        for col in range(start, reach, block):
            end = min(reach, col + block)
            cols = rows if col == start else flat[index[col:end]].astype(np.float32)
            dist2 = (norms[start:stop, None] + norms[None, col:end] - 2 * (rows @ cols.T)) / d
            pooled = (variances[start:stop, None] + variances[None, col:end]) / 2
            hits = (dist2 <= rms * rms + 1e-3) & (dist2 <= relative * relative * pooled + 1e-3)
            if col == start:
                hits = np.triu(hits, k=1)  # each pair once, no image with itself
            if hits.any():
                yield index[start:stop], index[col:end], hits


def near_duplicate_pairs(thumbs: np.ndarray, rms: float, relative: float) -> list[tuple[int, int]]:
    """All near-duplicate index pairs ``(i, j)``, ``i < j`` (:func:`near_duplicate_blocks`); for small sets."""
    pairs = []
    for rows, cols, hits in near_duplicate_blocks(thumbs, rms, relative):
        for a, b in zip(*np.nonzero(hits)):
            pairs.append(tuple(sorted((int(rows[a]), int(cols[b])))))
    return sorted(pairs)


def assign_groups(manifest: pd.DataFrame, thumbs: np.ndarray, rms: float, relative: float) -> tuple[list[str], dict, list[str]]:
    """Split group of every manifest row, duplicate counts and warnings.

    The group starts as the coarsest grouping the data gives within a class (instance, else session,
    else source), joins images sharing a pair key, then merges exact (MD5) and near-duplicates
    (:func:`near_duplicate_blocks`, same modality) of one class. A group is named after its
    smallest starting key. Duplicates across classes are counted and warned about, never merged."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(manifest)
    if n == 0:
        return [], {"exact_duplicate_files": 0, "near_duplicate_files": 0, "groups_before_merging": 0,
                    "groups_after_merging": 0, "files_identical_to_another_class": 0,
                    "near_duplicate_pairs_across_classes": 0}, []
    cls_codes, _ = pd.factorize(manifest["class"])
    md5_codes, _ = pd.factorize(manifest["md5"])
    cls = manifest["class"].to_numpy()
    keys = [f"{c}/{i}" if i else f"{c}/{s}" if s else src
            for c, i, s, src in zip(cls, manifest["instance"], manifest["session"], manifest["source"])]
    uf = _UnionFind(n)
    class_key = pd.Series(cls_codes).astype(str) + "\0"
    _union_equal(uf, pd.factorize(class_key + pd.Series(keys))[0])
    pairs = manifest["pair_key"].reset_index(drop=True)
    _union_equal(uf, np.where(pairs != "", pd.factorize(class_key + pairs)[0], -1))
    del class_key, pairs
    groups_before = len(np.unique(np.fromiter((uf.find(i) for i in range(n)), dtype=np.int64, count=n)))
    warnings = []
    path_of = manifest["path"]
    # exact duplicates: merged within a class
    exact = np.zeros(n, dtype=bool)
    cross_exact = 0
    first_in_class: dict[tuple[int, int], int] = {}
    first_any: dict[int, int] = {}
    for i in range(n):
        key = (md5_codes[i], cls_codes[i])
        if key in first_in_class:
            exact[i] = exact[first_in_class[key]] = True
            uf.union(first_in_class[key], i)
        else:
            first_in_class[key] = i
            j = first_any.setdefault(md5_codes[i], i)
            if j != i:  # the same bytes already seen in another class
                cross_exact += 1
                if cross_exact <= 5:
                    warnings.append(f"identical files in different classes (label noise?): {display_path(path_of.iat[j])} "
                                    f"({cls[j]}) and {display_path(path_of.iat[i])} ({cls[i]})")
    del first_in_class, first_any
    # near-duplicates, per modality: merged within a class, counted across classes
    near = np.zeros(n, dtype=bool)
    cross_near = 0
    for modality, rows in manifest.groupby("modality").indices.items():
        for r, c, hits in near_duplicate_blocks(thumbs, rms, relative, index=rows):
            same = cls_codes[r][:, None] == cls_codes[c][None, :]
            merge = hits & same
            new = merge & (md5_codes[r][:, None] != md5_codes[c][None, :])
            near[r[new.any(axis=1)]] = True
            near[c[new.any(axis=0)]] = True
            if merge.any():
                a, b = np.nonzero(merge)
                nodes = np.concatenate([r, c])
                graph = coo_matrix((np.ones(len(a)), (a, len(r) + b)), shape=(len(nodes), len(nodes)))
                _, labels = connected_components(graph, directed=False)
                firsts: dict[int, int] = {}
                for node, label in zip(nodes, labels):
                    uf.union(firsts.setdefault(int(label), int(node)), int(node))
            across = hits & ~same
            if across.any():
                for a, b in zip(*np.nonzero(across)):
                    cross_near += 1
                    if cross_near <= 5:
                        i, j = int(r[a]), int(c[b])
                        warnings.append(f"near-duplicate {modality} images in different classes (label noise?): "
                                        f"{display_path(path_of.iat[i])} ({cls[i]}) and "
                                        f"{display_path(path_of.iat[j])} ({cls[j]})")
    if cross_exact > 5 or cross_near > 5:
        warnings.append(f"in all: {cross_exact} file(s) identical to a file of another class and {cross_near} "
                        f"near-duplicate pair(s) across classes; they are not merged (a group never spans classes)")
    roots = np.fromiter((uf.find(i) for i in range(n)), dtype=np.int64, count=n)
    name_of: dict[int, str] = {}
    for i, root in enumerate(roots.tolist()):
        if root not in name_of or keys[i] < name_of[root]:
            name_of[root] = keys[i]
    counts = {"exact_duplicate_files": int(exact.sum()), "near_duplicate_files": int((near & ~exact).sum()),
              "groups_before_merging": groups_before, "groups_after_merging": len(name_of),
              "files_identical_to_another_class": cross_exact, "near_duplicate_pairs_across_classes": cross_near,
              "near_duplicate_rule": f"{THUMB}x{THUMB} greyscale thumbnails within {rms} grey levels RMS and "
                                     f"{relative} of their contrast, same class and modality"}
    return [name_of[root] for root in roots.tolist()], counts, warnings


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


def ingest_dataset(root: str | Path, dataset: str | dict, workers: int = 2, progress: bool = True
                   ) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """Read the dataset at ``root`` as ``dataset`` describes it (a preset name or the params section).

    Returns (manifest, quarantine, summary). Raises IngestError naming the folder when the folder is
    missing, the description is wrong, or nothing usable is left (then with the quarantine and summary).
    """
    root = Path(root)
    spec = _dataset_spec(dataset)
    source = spec["source"]
    if not root.is_dir():
        raise IngestError(f"{display_path(root)}: dataset folder does not exist")
    if not is_utf8_path(root.resolve()):
        raise IngestError(f"{display_path(root.resolve())}: the dataset folder's path is not valid UTF-8 text, "
                          f"so its files cannot be recorded; rename it")
    near = {**DEFAULT_NEAR_DUPLICATES, **(spec.get("near_duplicates") or {})}
    started = time.perf_counter()
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
    entries_in = len(candidates) + len(quarantined)
    decoded = len(candidates)
    columns: dict[str, list] = {name: [] for name in [*MANIFEST_COLUMNS, "instance", "session"]}
    thumbs = np.empty((decoded, THUMB, THUMB), dtype=np.uint8)
    kept = 0
    # our workers are the parallelism: OpenCV's own thread pool (thumbnails) on top of them only adds contention
    opencv_threads = cv2.getNumThreads()
    cv2.setNumThreads(1 if workers > 1 else opencv_threads)
    try:
        for result in stream_map(_inspect, candidates, workers, decoded, "ingest", progress):
            if "reason" in result:
                quarantined.append(result)
                continue
            thumbs[kept] = result.pop("thumb")
            kept += 1
            for name, values in columns.items():
                values.append(result[name])
    finally:
        cv2.setNumThreads(opencv_threads)
    del candidates
    thumbs = thumbs[:kept]
    manifest = pd.DataFrame(columns)
    del columns
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
    """Stage entry: write manifest.parquet, quarantine.parquet/.csv and summary.json into ``out_dir``.

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
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
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
