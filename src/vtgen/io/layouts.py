"""The dataset description: path patterns with named fields, presets, modality aliases and split names.

:func:`compile_layout` turns the ``dataset`` params section (or a preset, :data:`PRESETS`) into a
:class:`Layout`; :func:`match_file` reads one file's path (relative to ``dataset.path``) into a
:class:`Candidate` or the reason it cannot be used, and :func:`folder_problem` says why a folder cannot
hold data of the layout. The pattern syntax is described in :mod:`vtgen.stages.ingest` and docs/data.md.
Errors in the description are ValueErrors naming the params key.
"""

from __future__ import annotations

import functools
import os
import re
from dataclasses import dataclass, field

from vtgen.core.domain import MODALITIES

MODALITY_ALIASES = {
    "visual": "visual", "vision": "visual", "camera": "visual", "rgb": "visual", "v": "visual",
    "tactile": "tactile", "touch": "tactile", "gelsight": "tactile", "t": "tactile",
}
KNOWN_FIELDS = ("class", "modality", "split", "pair", "instance", "session", "source")
TEMPLATE_KEYS = ("source", "pair", "instance", "session")
SPLIT_NAMES = {"": "train", "train": "train", "training": "train", "val": "val", "valid": "val",
               "validation": "val", "dev": "val", "test": "test", "testing": "test"}

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


def modality_rules(dataset: dict) -> tuple[dict[str, str], str]:
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
    aliases, fixed = modality_rules(dataset)
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


def interpret(values: dict[str, str], layout: Layout, rel: str, templates: dict[str, str], note: str,
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


def match_file(rel: str, layout: Layout, path: str) -> Candidate | tuple[str, str, str]:
    """Match one file (path relative to the root) against the layout: a Candidate or (class, modality, reason)."""
    for pattern in layout.patterns:
        found = pattern.regex.match(rel)
        if found:
            values = {k: v for k, v in found.groupdict().items() if v is not None}
            result = interpret(values, layout, rel, pattern.templates, pattern.note, path)
            if isinstance(result, str):
                return values.get("class", ""), layout.aliases.get(values.get("modality", "").lower(), ""), result
            return result
    parts = rel.split("/")
    first = layout.patterns[0]
    if len(parts) == 1 and len(first.segments) > 1:
        return "", "", f"image at the top level; the layout '{layout.text}' expects folders"
    problem = folder_problem(parts[:-1], layout)
    if problem:
        return "", "", problem
    if len(parts) < len(first.segments):
        return "", "", f"is a file, not a folder; the layout '{layout.text}' expects a folder here"
    return "", "", f"does not match the layout '{layout.text}'"


def folder_problem(parts: list[str], layout: Layout) -> str:
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
