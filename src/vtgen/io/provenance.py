"""What produced an output: the vtgen source files a module runs, their fingerprint, the git version.

A cache keyed on "the code that produced it" (training checkpoints, study work folders) and the
stage table's code dependencies both come from :func:`code_files`, which follows a module's
imports inside the ``vtgen`` package.
"""

from __future__ import annotations

import ast
import hashlib
import subprocess
from functools import lru_cache
from pathlib import Path

PACKAGE_ROOT = Path(__file__).resolve().parents[1]


def module_file(module: str) -> Path | None:
    """The source file of a ``vtgen`` module (a package's ``__init__.py``), or None if it is not one."""
    parts = module.split(".")
    if parts[0] != "vtgen":
        return None
    base = PACKAGE_ROOT.joinpath(*parts[1:])
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


@lru_cache(maxsize=None)
def _imported_modules(path: Path, module: str) -> set[str]:
    """Every ``vtgen`` module that ``path`` imports (top level and inside functions)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)  # `from vtgen.core import metrics`
    return {m for m in found if m.startswith("vtgen") and module_file(m) is not None}


@lru_cache(maxsize=None)
def code_files(module: str) -> tuple[Path, ...]:
    """The source files ``module`` runs: itself, the ``vtgen`` modules it imports, transitively, and the
    ``__init__.py`` of every package on the way (Python executes them on import)."""
    seen: dict[str, Path] = {}
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = module_file(name)
        if path is None:
            raise ValueError(f"stage module {name} has no source file under {PACKAGE_ROOT}")
        seen[name] = path
        parents = [".".join(name.split(".")[:i]) for i in range(1, len(name.split(".")))]
        todo.extend(parents + sorted(_imported_modules(path, name)))
    return tuple(sorted(set(seen.values())))


def code_fingerprint(module: str) -> str:
    """SHA-256 over the source of every file ``module`` runs (:func:`code_files`): what a cache keyed on
    'the code that produced it' compares."""
    digest = hashlib.sha256()
    for path in code_files(module):
        digest.update(path.relative_to(PACKAGE_ROOT).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()


def code_version() -> str:
    """``<commit> (+ uncommitted changes)`` of the project's git checkout, or 'unknown'."""
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, check=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown (not a git checkout)"
    return commit + (" (+ uncommitted changes)" if dirty else "")
