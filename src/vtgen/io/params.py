"""Load and validate params.yaml, the one configuration shared by Snakemake and DVC.

The schema is ``params.schema.yaml`` beside this module (package data); every key is required and
unknown keys are refused, so a typo stops a run at start with the key named.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import jsonschema
import yaml

from vtgen.core.domain import DIRECTIONS

SCHEMA_PATH = Path(__file__).with_name("params.schema.yaml")  # package data: ships with every install
SYNTHETIC_PATH = "data/raw/synthetic"


class ParamsError(ValueError):
    """params.yaml is missing, unparsable or does not match the schema."""


def _key_path(error: jsonschema.ValidationError) -> str:
    return ".".join(str(p) for p in error.absolute_path) or "<top level>"


def validate_params(params: Any, source: str = "params.yaml") -> dict:
    """Check ``params`` against the schema; return it unchanged or raise ParamsError.

    The message names every offending key, e.g. ``roi.size: 'big' is not of type 'integer'``
    or ``roi: unknown key 'sise'``.
    """
    schema = yaml.safe_load(SCHEMA_PATH.read_text())
    validator = jsonschema.Draft202012Validator(schema)
    problems = []
    errors = [leaf for error in validator.iter_errors(params) for leaf in _mapping_errors(error)]
    for error in sorted(errors, key=lambda e: [str(part) for part in e.absolute_path]):
        if error.validator == "additionalProperties":
            known = set(error.schema.get("properties", {}))
            for key in sorted(set(error.instance) - known):
                problems.append(f"{_key_path(error)}: unknown key '{key}' (allowed: {', '.join(sorted(known))})")
        elif error.validator == "required":
            problems.append(f"{_key_path(error)}: {error.message}")
        else:
            problems.append(f"{_key_path(error)}: {error.message}")
    if not problems:
        problems += [f"{key}: {value!r} is not a finite number" for key, value in _non_finite(params)]
    if not problems and params["dataset"]["source"] == "synthetic" and params["dataset"]["path"] != SYNTHETIC_PATH:
        problems.append(
            f"dataset.path: must be '{SYNTHETIC_PATH}' when dataset.source is 'synthetic' "
            f"(the render stage writes there), got '{params['dataset']['path']}'"
        )
    if not problems:
        problems += _translation_problems(params)
    if not problems:
        problems += _study_problems(params, validator)
    if not problems:
        problems += _recipe_problems(params, validator)
    if problems:
        raise ParamsError(f"{source} is invalid:\n  " + "\n  ".join(problems))
    return params


def _mapping_errors(error: jsonschema.ValidationError) -> list[jsonschema.ValidationError]:
    """``error``, or where a value that may be given per direction (one of several forms, e.g. a number or
    ``{v2t: w, t2v: w}``) is a mapping the mapping's own form refuses, that form's errors: they name the key at
    fault (``translation.class_gan.r1.v2t: 'twelve' is not of type 'number'``) where the whole error would not."""
    if error.validator not in ("oneOf", "anyOf") or not isinstance(error.instance, dict):
        return [error]
    inner = [e for e in error.context if e.relative_path or e.validator in ("required", "additionalProperties")]
    return [leaf for e in inner for leaf in _mapping_errors(e)] or [error]


def _non_finite(value: Any, key: str = "") -> list[tuple[str, float]]:
    """(dotted key, value) of every NaN or infinite float in ``value`` (JSON schema bounds let them through)."""
    if isinstance(value, float):
        return [] if math.isfinite(value) else [(key, value)]
    if isinstance(value, dict):
        return [hit for k, v in value.items() for hit in _non_finite(v, f"{key}.{k}" if key else str(k))]
    if isinstance(value, list):
        return [hit for i, v in enumerate(value) for hit in _non_finite(v, f"{key}[{i}]")]
    return []


def _translation_problems(params: dict) -> list[str]:
    """Cross-key checks of the translation section that the schema cannot express."""
    problems = []
    preset, presets = params["translation"]["preset"], params["presets"]
    if preset not in presets:
        problems.append(f"translation.preset: '{preset}' is not a block of presets (defined: {', '.join(presets)})")
    if params["dataset"]["source"] == "synthetic":
        classes = set(params["synthetic"]["classes"])
        for entry in params["translation"]["scope"]:
            if entry != "all" and entry not in classes:
                problems.append(f"translation.scope: '{entry}' is neither 'all' nor one of synthetic.classes")
    return problems


def resolve_key(params: dict, key: str) -> str:
    """A study override's key in params: ``preset.x`` -> ``presets.<translation.preset>.x``, others unchanged."""
    if key.startswith("preset."):
        return f"presets.{params['translation']['preset']}.{key[len('preset.'):]}"
    return key


def _study_problems(params: dict, validator: jsonschema.Draft202012Validator) -> list[str]:
    """Every override under ``studies`` must name an existing key and give it a value the schema accepts,
    so a typo stops the run at start rather than when the study reaches it."""
    studies = params["studies"]
    groups = [("studies.experiments.base", studies["experiments"]["base"]),
              ("studies.tradeoff.base", studies["tradeoff"]["base"])]
    groups += [(f"studies.experiments.runs.{n}.set", r["set"]) for n, r in studies["experiments"]["runs"].items()]
    groups += [(f"studies.tradeoff.settings.{n}", o) for n, o in studies["tradeoff"]["settings"].items()]
    return [problem for where, overrides in groups for problem in _override_problems(params, validator, where, overrides)]


def _override_problems(params: dict, validator: jsonschema.Draft202012Validator, where: str, overrides: dict) -> list[str]:
    """What is wrong with the dotted-key ``overrides`` found at ``where``: a key params does not have, or a value
    the schema refuses there."""
    problems = []
    for key, value in overrides.items():
        parts = resolve_key(params, key).split(".")
        node = params
        for part in parts[:-1]:
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict) or parts[-1] not in node:
            problems.append(f"{where}.{key}: params has no key '{'.'.join(parts)}'")
            continue
        trial = {**params, parts[0]: copy.deepcopy(params[parts[0]])}
        target = trial
        for part in parts[:-1]:
            target = target[part]
        target[parts[-1]] = value
        errors = [e for e in validator.iter_errors(trial) if list(e.absolute_path)[:len(parts)] == parts]
        if errors:  # the deepest reason, so a per-direction value's bad entry is named, not only its block
            error = jsonschema.exceptions.best_match(errors)
            inner = "".join(f".{part}" for part in list(error.absolute_path)[len(parts):])
            problems.append(f"{where}.{key}{inner}: {error.message}")
        problems += [f"{where}.{key}: {v!r} is not a finite number" for _, v in _non_finite(value)]
    return problems


# What a recipe may set: the stages that read these keys (settings, generate, report, the studies) also depend on
# ``recipes``. The keys that shape the workflow itself (which jobs exist, their threads) or
# that other stages read are not a recipe's to change.
RECIPE_SECTIONS = ("translation.", "generate.", "preset.")
RECIPE_FORBIDDEN = ("translation.preset", "translation.recipe", "translation.scope", "translation.device",
                    "translation.threads")


def _recipe_problems(params: dict, validator: jsonschema.Draft202012Validator) -> list[str]:
    """``translation.recipe`` must name a block of ``recipes`` (or be ``auto``, which needs the blocks it chooses
    among); each block sets existing translation, generate or
    preset keys to values the schema accepts."""
    recipes, chosen = params["recipes"], params["translation"]["recipe"]
    problems = []
    if AUTO_RECIPE in recipes:
        problems.append(f"recipes.{AUTO_RECIPE}: '{AUTO_RECIPE}' is translation.recipe's choice from the data, not a block name")
    if chosen == AUTO_RECIPE:
        missing = [name for name in AUTO_CHOICES if name not in recipes]
        if missing:
            problems.append(f"translation.recipe: 'auto' chooses among {', '.join(AUTO_CHOICES)}; recipes has no "
                            f"block {', '.join(missing)}")
    elif chosen not in recipes:
        problems.append(f"translation.recipe: '{chosen}' is not a block of recipes (defined: {', '.join(recipes)}, "
                        f"or {AUTO_RECIPE})")
    for name, overrides in recipes.items():
        allowed = {}
        for key, value in overrides.items():
            if not key.startswith(RECIPE_SECTIONS):
                problems.append(f"recipes.{name}: unknown key '{key}' (a recipe sets translation.*, generate.* or "
                                f"preset.* keys)")
            elif key in RECIPE_FORBIDDEN:
                problems.append(f"recipes.{name}.{key}: set it in params.yaml itself (it decides which jobs run and "
                                f"where, or which recipe applies)")
            else:
                allowed[key] = value
        problems += _override_problems(params, validator, f"recipes.{name}", allowed)
    return problems


def set_keys(params: dict, overrides: dict) -> dict:
    """A deep copy of ``params`` with each dotted key of ``overrides`` (``preset.x`` = the chosen preset's x) set
    to its value; a key params does not have is a ValueError naming it. Not validated."""
    merged = copy.deepcopy(params)
    for raw_key, value in overrides.items():
        key = resolve_key(params, raw_key)
        node, parts = merged, key.split(".")
        for depth, part in enumerate(parts[:-1]):
            if not isinstance(node, dict) or part not in node:
                raise ValueError(f"override '{raw_key}': params has no key '{'.'.join(parts[:depth + 1])}'")
            node = node[part]
        if not isinstance(node, dict) or parts[-1] not in node:
            raise ValueError(f"override '{raw_key}': params has no key '{key}'")
        node[parts[-1]] = copy.deepcopy(value)
    return merged


# translation.recipe auto: the fabric recipe when every training pair is a class pair and the training photos are
# textures (layout gap at most this; vtgen.core.layout: 0.13 on the synthetic fabrics, 0.17 on real ViTac cloth,
# 0.76 on vt60_subset's objects), else none (benchmarks/README.md, Thirty-ninth round)
AUTO_RECIPE = "auto"
AUTO_CHOICES = ("fabric", "none")
TEXTURE_LAYOUT_GAP = 0.4


def recipe_choice(params: dict, data_kind: dict | None) -> tuple[str, str]:
    """The block of ``recipes`` a run applies, and why. ``translation.recipe`` as set unless ``auto``, which reads
    ``data_kind`` (the pairs stage's summary.json): ``fabric`` when every training pair of both directions is a
    class pair, the training split has two classes or more and the training photos' median layout gap is at most ``TEXTURE_LAYOUT_GAP``, else ``none``;
    without ``data_kind`` (a stage before pairing, or one that reads no pairs) ``none``."""
    chosen = params["translation"]["recipe"]
    if chosen != AUTO_RECIPE:
        return chosen, "as set"
    if data_kind is None:
        return "none", "auto: no pairs summary read by this stage"
    if not data_kind.get("class_pairs_only"):
        return "none", "auto: some training pairs are pixel or name pairs (pix2pix trains; the recipes are for class pairs)"
    if data_kind.get("classes", 0) < 2:
        return "none", "auto: one class (the fabric recipe's generators are told the class a reader reads)"
    gap = data_kind.get("layout_gap")
    if gap is None:
        return "none", "auto: no training photos to tell textures from scenes"
    if gap <= TEXTURE_LAYOUT_GAP:
        return "fabric", (f"auto: class pairs only, and the training photos are textures (layout gap {gap:.2f}, "
                          f"at most {TEXTURE_LAYOUT_GAP})")
    return "none", f"auto: class pairs only, but the training photos are scenes (layout gap {gap:.2f}, above {TEXTURE_LAYOUT_GAP})"


def with_recipe(params: dict, data_kind: dict | None = None) -> dict:
    """The settings the stages run with: validated ``params`` with the block of ``recipes`` that
    :func:`recipe_choice` picks applied over them (``none``: unchanged values). ``translation.recipe`` becomes the
    chosen block's name, so applying it twice changes nothing."""
    chosen, _ = recipe_choice(params, data_kind)
    if chosen == params["translation"]["recipe"] and not params["recipes"][chosen]:
        return params
    named = set_keys(params, {"translation.recipe": chosen})
    return validate_params(set_keys(named, params["recipes"][chosen]), source=f"params.yaml with recipe '{chosen}'")


def model_settings(params: dict) -> dict:
    """The preset block that translation.preset names: network and training settings."""
    return params["presets"][params["translation"]["preset"]]


def for_direction(value: Any, direction: str) -> Any:
    """``value`` as ``direction`` reads it: a value given per direction (a mapping of exactly v2t and t2v) becomes
    ``direction``'s; mappings are walked; anything else is returned as it is."""
    if isinstance(value, dict):
        if set(value) == set(DIRECTIONS):
            return for_direction(value[direction], direction)
        return {key: for_direction(item, direction) for key, item in value.items()}
    return value


def direction_settings(params: dict, direction: str, data_kind: dict | None = None) -> dict:
    """Every params value the train stage of ``direction`` reads: the ``translation`` section with the recipe
    applied (:func:`with_recipe`) and each per-direction value as ``direction``'s, the preset block it names, and
    ``roi``. Two directions' settings differ only where params gives them different values, so the settings
    stage's record of one direction stays byte-identical when only the other's values change."""
    applied = with_recipe(params, data_kind)
    return {"translation": for_direction(applied["translation"], direction), "preset": model_settings(applied),
            "roi": applied["roi"]}


def settings_record(params: dict, direction: str) -> dict:
    """What ``direction``'s settings depend on in params alone (Snakemake's record of the settings job, taken before
    any data exists): :func:`direction_settings`, or under ``translation.recipe: auto`` those of each block auto may
    choose, so that editing either block reruns the job and a value for the other direction does not."""
    if params["translation"]["recipe"] != AUTO_RECIPE:
        return direction_settings(params, direction)
    return {name: direction_settings(set_keys(params, {"translation.recipe": name}), direction) for name in AUTO_CHOICES}


def load_params(path: str | Path = "params.yaml") -> dict:
    """Read a params YAML file and validate it; raise ParamsError naming the file and key."""
    path = Path(path)
    if not path.is_file():
        raise ParamsError(f"{path}: no such params file")
    try:
        params = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ParamsError(f"{path}: not valid YAML: {exc}") from exc
    return validate_params(params, source=str(path))
