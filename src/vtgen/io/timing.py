"""Run times, kept apart from the data: each stage's ``timing.json`` in its output folder.

A stage command writes its wall time, date and peak memory there (vtgen.cli), after the stage's own times
(images per second, seconds per training step, the step a run resumed from). Up to generate no other output file
holds a time (classify and score give the seconds of their parts), and neither DVC (.dvcignore) nor the content
records (:mod:`vtgen.io.contents`) hash ``timing.json``: a stage that runs again and writes the same data leaves
the stages after it with nothing to do.
"""

from __future__ import annotations

import json
from pathlib import Path

TIMING = "timing.json"
COMMAND_TIMES = ("stage", "seconds", "finished")  # what vtgen.cli adds to a timing.json, beside peak_* memory


def split_times(record: dict, keys: set[str]) -> tuple[dict, dict]:
    """``record`` without the entries named in ``keys`` at any depth of its nested dicts, and those entries in the
    same nesting: (data, times). :func:`merge_times` of the two gives ``record`` back."""
    data, times = {}, {}
    for key, value in record.items():
        if key in keys:
            times[key] = value
        elif isinstance(value, dict):
            data[key], inner = split_times(value, keys)
            if inner:
                times[key] = inner
        else:
            data[key] = value
    return data, times


def merge_times(record: dict, times: dict) -> dict:
    """``record`` with the entries of ``times`` put back at their nesting (the inverse of :func:`split_times`)."""
    merged = dict(record)
    for key, value in times.items():
        merged[key] = merge_times(merged[key], value) if isinstance(value, dict) and isinstance(merged.get(key), dict) \
            else value
    return merged


def read_with_times(path: str | Path) -> dict:
    """The JSON record at ``path`` with the stage's own times from the timing.json beside it put back where
    :func:`split_times` took them from (the command's wall time, date and memory left out); as written when the
    folder has no timing.json (a copy without it)."""
    timing = Path(path).with_name(TIMING)
    try:
        record = json.loads(Path(path).read_text())
        times = json.loads(timing.read_text()) if timing.is_file() else {}
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path} or the {TIMING} beside it cannot be read: {exc}") from exc
    return merge_times(record, {k: v for k, v in times.items() if k not in COMMAND_TIMES and not k.startswith("peak_")})


def write_timing(folder: str | Path, times: dict) -> None:
    """A stage's own times (``times``: seconds, images per second, ...) into ``folder``/timing.json, where the stage
    command adds its wall time and peak memory (vtgen.cli); never into a file that is hashed as data."""
    (Path(folder) / TIMING).write_text(json.dumps(times) + "\n")
