"""One run at a time per project: Snakemake and DVC exclude each other.

The lock is an ``flock`` on ``.vtgen/run.lock`` in the project root. The kernel releases it when
the holder exits, however it exits, so a killed run never leaves a lock that needs a manual
unlock. A Snakemake run holds it from its start (``onstart``) to its end and passes the right to
run to its jobs through :data:`OWNER_ENV`; a stage command started by anything else (``dvc
repro``, ``dvc exp run``, a user) takes the lock itself for as long as it runs.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import time
from collections.abc import Iterator
from pathlib import Path

LOCK_PATH = Path(".vtgen") / "run.lock"
OWNER_ENV = "VTGEN_RUN_OWNER"
_held: dict[Path, object] = {}  # lock path -> open handle: the lock lives while this process keeps it


class ProjectBusy(RuntimeError):
    """Another Snakemake or DVC run of this project is in progress."""


def _owner(path: Path) -> dict:
    try:
        return json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}


def hold_run_lock(tool: str, root: str | Path = ".") -> None:
    """Take the project's run lock for this process (until it exits) or raise ProjectBusy naming the holder."""
    path = (Path(root) / LOCK_PATH).resolve()
    if path in _held:
        return  # this process holds it already
    if os.environ.get(OWNER_ENV) and _owner(path).get("pid") == int(os.environ[OWNER_ENV]) \
            and os.environ[OWNER_ENV] != str(os.getpid()):
        return  # a job of the run that holds the lock
    path.parent.mkdir(exist_ok=True)
    handle = open(path, "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _owner(path)
        handle.close()
        raise ProjectBusy(
            f"{path}: another run of this project is in progress ({holder.get('tool', 'unknown tool')}, "
            f"pid {holder.get('pid', '?')}, since {holder.get('since', '?')}); wait for it to finish or stop it, "
            f"then run again (Snakemake and DVC share the outputs, so they never run at once)") from None
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps({"tool": tool, "pid": os.getpid(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
    handle.flush()
    _held[path] = handle
    os.environ[OWNER_ENV] = str(os.getpid())


def release_run_lock(root: str | Path = ".") -> None:
    """Give the lock back (a process that exits gives it back anyway)."""
    handle = _held.pop((Path(root) / LOCK_PATH).resolve(), None)
    if handle is not None:
        handle.close()
        if os.environ.get(OWNER_ENV) == str(os.getpid()):
            del os.environ[OWNER_ENV]


@contextlib.contextmanager
def run_lock(tool: str, root: str | Path = ".") -> Iterator[None]:
    """Hold the run lock for the ``with`` block, unless this process or the run that started it holds it."""
    path = (Path(root) / LOCK_PATH).resolve()
    already = path in _held
    hold_run_lock(tool, root)
    try:
        yield
    finally:
        if not already:
            release_run_lock(root)
