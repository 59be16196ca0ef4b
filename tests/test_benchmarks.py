"""The benchmark scripts stay runnable: each compiles, and each with a command line (argparse) imports what it
needs from vtgen and prints its usage. They are run by hand, so nothing else would notice one broken by a rename
or a typo until the next person needs its table."""

from __future__ import annotations

import subprocess
import sys

import pytest

from conftest import REPO

SCRIPTS = sorted((REPO / "benchmarks").glob("*.py"))


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.name)
def test_benchmark_script_compiles_and_prints_its_usage(script):
    compile(script.read_text(), str(script), "exec")  # a SyntaxError names the file and line
    if "argparse" not in script.read_text():
        return  # e.g. train_loop_ab.py takes a checkout path, not options
    done = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120,
                          cwd=REPO)
    assert done.returncode == 0 and done.stdout.startswith("usage:"), (script.name, done.stderr[-2000:])


def test_every_benchmark_script_is_found():
    assert len(SCRIPTS) >= 20 and any(p.name == "unaligned_ablation.py" for p in SCRIPTS)
