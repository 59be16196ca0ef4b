"""Content records: what a job read and wrote, by md5, so that a run can tell intact outputs from damaged ones
and changed inputs from touched ones, as DVC does.

Every stage command ends by writing ``.contents.json`` into its output folder (the report: into
``reports/figures``): the md5 and size of each file it wrote, and a hash of each input it read (a folder's
hash covers the relative path and md5 of every file below it). The record travels with the output (DVC
caches it, ``dvc pull`` restores it), so it stays true of the files beside it.

md5s are kept in a stat cache (``.vtgen/hashes.json``, keyed by path, size, mtime and inode, as DVC's own
state): a file is read again only when one of those changed. A same-size edit that also keeps the file's
mtime and inode is therefore not seen (DVC has the same blind spot).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from pathlib import Path

from vtgen.io.timing import TIMING

RECORD = ".contents.json"
# our record, the run's timings and Snakemake's directory marker are not data (.dvcignore lists the same for DVC), so
# a stage that reruns and writes the same data leaves the stages after it with nothing to do
NOT_CONTENT = {RECORD, TIMING, ".snakemake_timestamp"}
CACHE = Path(".vtgen") / "hashes.json"


class Hasher:
    """md5 of files and folders through the stat cache of ``root``/.vtgen/hashes.json; :meth:`save` keeps it."""

    def __init__(self, root: str | Path = "."):
        self.root = Path(root)
        self.cache_path = self.root / CACHE
        try:
            self.cache: dict[str, list] = json.loads(self.cache_path.read_text())
        except (OSError, ValueError):
            self.cache = {}
        self.changed = False

    def file(self, path: str | Path) -> str | None:
        """md5 of the file at ``path`` (links followed), None when it is missing or unreadable."""
        try:
            st = os.stat(path)
        except OSError:
            return None
        key = os.path.abspath(path)
        stamp = [st.st_size, st.st_mtime_ns, st.st_ino]
        known = self.cache.get(key)
        if known and known[:3] == stamp:
            return known[3]
        digest = hashlib.md5()
        try:
            with open(path, "rb") as handle:
                while chunk := handle.read(1 << 20):
                    digest.update(chunk)
        except OSError:
            return None
        self.cache[key] = [*stamp, digest.hexdigest()]
        self.changed = True
        return digest.hexdigest()

    def files(self, folder: str | Path) -> dict[str, str | None]:
        """Relative path -> md5 of every file below ``folder`` (folder links followed once), records left out."""
        found: dict[str, str | None] = {}
        seen: set[str] = set()
        for base, dirs, names in os.walk(folder, followlinks=True):
            real = os.path.realpath(base)
            if real in seen:
                dirs[:] = []
                continue
            seen.add(real)
            dirs.sort()
            for name in sorted(names):
                if name not in NOT_CONTENT:
                    path = os.path.join(base, name)
                    found[os.path.relpath(path, folder)] = self.file(path)
        return found

    def hash(self, path: str | Path) -> str | None:
        """md5 of a file, or of a folder's listing of relative paths and md5s; None when missing."""
        if os.path.isdir(path):
            listing = "".join(f"{rel}\0{md5}\n" for rel, md5 in sorted(self.files(path).items()))
            return hashlib.md5(listing.encode("utf-8", "surrogateescape")).hexdigest()
        return self.file(path)

    def save(self) -> None:
        if not self.changed:
            return
        with contextlib.suppress(OSError):  # a cache: losing it costs time, never correctness
            self.cache_path.parent.mkdir(exist_ok=True)
            tmp = self.cache_path.with_name(f"{self.cache_path.name}.{os.getpid()}.tmp")
            tmp.write_text(json.dumps(self.cache))
            tmp.replace(self.cache_path)
        self.changed = False


def output_files(outputs: list[str], hasher: Hasher) -> dict[str, list]:
    """Project-relative path -> [size, md5] of every file of ``outputs`` (files or folders)."""
    found: dict[str, list] = {}
    for out in outputs:
        if os.path.isdir(out):
            for rel, md5 in hasher.files(out).items():
                path = os.path.join(out, rel)
                found[Path(path).as_posix()] = [os.path.getsize(path), md5]
        elif os.path.exists(out):
            found[Path(out).as_posix()] = [os.path.getsize(out), hasher.file(out)]
    return found


def write_record(where: str | Path, job: str, inputs: dict[str, str | None], outputs: list[str],
                 hasher: Hasher) -> None:
    """Write ``where``/.contents.json: the job's name, its input hashes and the files of its outputs."""
    record = {"job": job, "inputs": inputs, "outputs": output_files(outputs, hasher)}
    target = Path(where) / RECORD
    tmp = target.with_name(f"{RECORD}.tmp")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    tmp.replace(target)
    hasher.save()


def read_record(where: str | Path) -> dict | None:
    """The record in ``where``, or None when there is none or it cannot be read (then nothing is known)."""
    try:
        record = json.loads((Path(where) / RECORD).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and {"inputs", "outputs"} <= set(record) else None


def damage(record: dict, outputs: list[str], hasher: Hasher) -> str | None:
    """What differs between ``outputs`` on disk and ``record`` (the first difference, in words), or None."""
    recorded = record["outputs"]
    present = output_files(outputs, hasher)
    for path, (size, md5) in recorded.items():
        if path not in present:
            return f"{path} is missing"
        if present[path][0] != size:
            return f"{path} has {present[path][0]} bytes, {size} when written"
        if present[path][1] != md5:
            return f"{path} differs from what was written (md5)"
    extra = sorted(set(present) - set(recorded))
    return f"{extra[0]} was not written by the job" if extra else None
