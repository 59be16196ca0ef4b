"""One run at a time per project: Snakemake and DVC exclude each other.

Two ``flock`` files in ``.vtgen/``; the kernel releases a lock when its holder exits, however it
exits, so a killed run never leaves a lock that needs a manual unlock.

- ``run.lock``, held exclusively by whoever drives a run: a Snakemake run from its start
  (``onstart``) to its end, or a stage command started by anything else (``dvc repro``, ``dvc exp
  run``, a user) for as long as it runs. A second driver is refused with a message naming the first.
- ``jobs.lock``, held shared by every running stage command, each of which also leaves its pid in
  ``jobs/<pid>``. A new driver stops the jobs a killed Snakemake left running (SIGTERM; the run
  it drives redoes them, training from its last checkpoint) and waits until nobody holds the lock,
  so no orphaned job writes beside the new run.

A Snakemake run passes the right to run to its jobs through :data:`OWNER_ENV`.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path

LOCK_DIR = Path(".vtgen")
OWNER_ENV = "VTGEN_RUN_OWNER"
_held: dict[Path, object] = {}  # lock path -> open handle: a lock lives while this process keeps its handle


class ProjectBusy(RuntimeError):
    """Another Snakemake or DVC run of this project is in progress."""


def _owner(path: Path) -> dict:
    try:
        return json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}


def _open(path: Path):
    path.parent.mkdir(exist_ok=True)
    return open(path, "a+")


def _orphaned_pids(records: Path) -> list[int]:
    """Pids recorded in ``records`` whose process is still a running vtgen command."""
    alive = []
    for record in records.glob("*"):
        try:
            pid = int(record.name)
            if b"vtgen" in Path(f"/proc/{pid}/cmdline").read_bytes():
                alive.append(pid)
        except (ValueError, OSError):
            continue
    return sorted(alive)


def _stop_orphaned_jobs(jobs: Path) -> None:
    """Stop the stage commands a killed run left running, then block until none holds ``jobs.lock``."""
    with _open(jobs) as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pids = _orphaned_pids(jobs.with_name("jobs"))
            print(f"vtgen: stopping {len(pids)} stage command(s) left running by an earlier, killed run "
                  f"(pids {', '.join(map(str, pids)) or 'unknown'}); this run redoes their work", file=sys.stderr,
                  flush=True)
            for pid in pids:
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGTERM)
            fcntl.flock(handle, fcntl.LOCK_EX)
        fcntl.flock(handle, fcntl.LOCK_UN)


def hold_run_lock(tool: str, root: str | Path = ".") -> None:
    """Drive a run: take ``run.lock`` for this process (until it exits or releases it), after any jobs of a
    killed run have finished; raise ProjectBusy naming the holder when another run is in progress."""
    path = (Path(root) / LOCK_DIR / "run.lock").resolve()
    if path in _held:
        return
    handle = _open(path)
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = _owner(path)
        handle.close()
        raise ProjectBusy(
            f"{path}: another run of this project is in progress ({holder.get('tool', 'unknown tool')}, "
            f"pid {holder.get('pid', '?')}, since {holder.get('since', '?')}); wait for it to finish or stop it, "
            f"then run again (Snakemake and DVC share the outputs, so they never run at once)") from None
    _stop_orphaned_jobs(path.with_name("jobs.lock"))
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps({"tool": tool, "pid": os.getpid(), "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
    handle.flush()
    _held[path] = handle
    os.environ[OWNER_ENV] = str(os.getpid())


def run_holder(root: str | Path = ".") -> str | None:
    """When another process holds ``run.lock`` now (a Snakemake or DVC run of this project is going on), that run
    as "tool, pid N, since T"; else None."""
    path = (Path(root) / LOCK_DIR / "run.lock").resolve()
    if path in _held or not path.exists():
        return None
    with open(path) as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _owner(path)
            return (f"{holder.get('tool', 'unknown tool')}, pid {holder.get('pid', '?')}, "
                    f"since {holder.get('since', '?')}")
    return None


def _release(path: Path) -> None:
    handle = _held.pop(path, None)
    if handle is not None:
        handle.close()


def _started_by_the_run(run: Path) -> bool:
    owner = os.environ.get(OWNER_ENV, "")
    return owner.isdigit() and owner != str(os.getpid()) and _owner(run).get("pid") == int(owner)


@contextlib.contextmanager
def run_lock(tool: str, root: str | Path = ".") -> Iterator[None]:
    """Hold what a stage command needs for the ``with`` block: ``jobs.lock`` shared, and ``run.lock`` too
    unless the Snakemake run that started this command (or this process) already drives the run."""
    run = (Path(root) / LOCK_DIR / "run.lock").resolve()
    jobs = run.with_name("jobs.lock")
    drive = run not in _held and not _started_by_the_run(run)
    if drive:
        hold_run_lock(tool, root)
    handle = _open(jobs)
    fcntl.flock(handle, fcntl.LOCK_SH)
    record = jobs.with_name("jobs") / str(os.getpid())
    record.parent.mkdir(exist_ok=True)
    record.write_text(tool)
    try:
        yield
    finally:
        record.unlink(missing_ok=True)
        handle.close()
        if drive:
            _release(run)
            if os.environ.get(OWNER_ENV) == str(os.getpid()):
                del os.environ[OWNER_ENV]
