"""Settings stage: the params values one direction's training reads, resolved, as a file.

Both tools decide reruns by what a stage depends on. The train stage reads the whole ``translation``
section, whose per-direction values (``{v2t: x, t2v: y}``) belong to one direction only; depending on the
section, changing T2V's value would retrain V2T too. This stage writes
:func:`vtgen.io.params.direction_settings` for one direction to ``<out>/train.json``, and the train stage
depends on that file instead of on params: DVC reruns both settings jobs on any change to the sections and
finds the other direction's file unchanged, so it skips that training; Snakemake's params record of this
stage is the same per-direction value (:mod:`vtgen.pipeline`), so it reruns only the changed direction.
"""

from __future__ import annotations

import json
from pathlib import Path

from vtgen.io.images import atomic_output_dir
from vtgen.io.params import direction_settings

SETTINGS_FILE = "train.json"


def settings_text(params: dict, direction: str) -> str:
    """The text of one direction's settings file: sorted JSON, so equal settings give equal bytes."""
    return json.dumps(direction_settings(params, direction), indent=2, sort_keys=True) + "\n"


def run_settings(params: dict, direction: str, out_dir: str | Path) -> None:
    """Stage entry: write ``out_dir``/train.json, the settings ``direction``'s training reads (atomically)."""
    with atomic_output_dir(out_dir) as tmp:
        (tmp / SETTINGS_FILE).write_text(settings_text(params, direction))
    print(f"settings {direction}: the values its training reads -> {Path(out_dir) / SETTINGS_FILE}")
