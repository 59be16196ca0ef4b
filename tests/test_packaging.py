"""Packaging: a regular (non-editable) install of vtgen works outside the source tree, and VTGEN_DEBUG
switches between the one-line error and the traceback.

The e2e tests build and install the project into a fresh venv (``python -m venv``; ``pip install
--no-deps``, offline through pip's configured find-links). The venv gets the dependencies from this
interpreter's site-packages through a plain path line in a .pth file: a path line does not make
Python read that folder's own .pth files, so this checkout's editable install (its src/ on the path)
is not picked up, and the tests check that ``vtgen`` is imported from the venv.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

import pytest
import yaml

from conftest import REPO
from vtgen.cli import main
from vtgen.io.params import ParamsError

FAILING = ["classify", "--modality", "visual", "--pairs", "data/pairs", "--generated", "data/generated", "--out", "out"]


def typo_params(folder: Path) -> Path:
    """The project's params.yaml with ``classify.lr`` misspelt ``classify.lrr``."""
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    params["classify"]["lrr"] = params["classify"].pop("lr")
    path = folder / "typo.yaml"
    path.write_text(yaml.safe_dump(params, sort_keys=False))
    return path


def test_cli_without_debug_prints_one_error_and_no_traceback(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("VTGEN_DEBUG", "0")
    assert main([*FAILING, "--params", str(typo_params(tmp_path))]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"vtgen classify: error: {tmp_path / 'typo.yaml'} is invalid:")
    assert "classify: unknown key 'lrr'" in err and "Traceback" not in err


def test_cli_with_debug_raises(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("VTGEN_DEBUG", "1")
    with pytest.raises(ParamsError, match="classify: unknown key 'lrr'"):
        main([*FAILING, "--params", str(typo_params(tmp_path))])
    assert "error:" not in capsys.readouterr().err


# --- a real install into a fresh venv ---------------------------------------------------------------------------

def copy_source(target: Path) -> Path:
    """The files a build reads (pyproject.toml, README.md, src/), so the build writes build/ and *.egg-info
    there and not into the shared checkout."""
    target.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, target / name)
    for extra in REPO.glob("LICENSE*"):
        shutil.copy(extra, target / extra.name)
    shutil.copytree(REPO / "src", target / "src", ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
    return target


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv, clean env, cwd outside the repo, seconds taken) for vtgen installed from a copy of this checkout."""
    root = tmp_path_factory.mktemp("packaging")
    started = time.perf_counter()
    source = copy_source(root / "source")
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, capture_output=True, timeout=300)
    python = venv / "bin" / "python"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME", "VTGEN_DEBUG")}
    env.update(PATH=f"{venv / 'bin'}{os.pathsep}{env['PATH']}", VIRTUAL_ENV=str(venv), PIP_DISABLE_PIP_VERSION_CHECK="1")
    build = subprocess.run([str(python), "-m", "pip", "install", "--no-deps", "--no-input", str(source)], env=env,
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, f"pip install failed:\n{build.stdout[-3000:]}\n{build.stderr[-3000:]}"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             env=env, capture_output=True, text=True, check=True).stdout.strip()
    dependencies = sysconfig.get_paths()["purelib"]  # this interpreter's: torch, pandas, jsonschema, ...
    (Path(purelib) / "vtgen_test_dependencies.pth").write_text(dependencies + "\n")
    cwd = root / "elsewhere"
    cwd.mkdir()
    assert REPO not in cwd.parents
    return venv, env, cwd, time.perf_counter() - started


def run_in(installed, *command: str) -> subprocess.CompletedProcess:
    venv, env, cwd, _ = installed
    return subprocess.run(list(command), cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.e2e
def test_install_imports_vtgen_from_the_venv_with_its_package_data(installed):
    venv = installed[0]
    code = ("import importlib.resources as r, vtgen, vtgen.io.params as p; print(vtgen.__file__); "
            "print(p.SCHEMA_PATH); print(r.files('vtgen.io').joinpath('params.schema.yaml').is_file())")
    result = run_in(installed, str(venv / "bin" / "python"), "-c", code)
    assert result.returncode == 0, result.stderr
    module, schema, found = result.stdout.split()
    assert Path(module).is_relative_to(venv) and Path(schema).is_relative_to(venv), result.stdout
    assert found == "True"
    installed_files = {p.relative_to(Path(module).parent) for p in Path(module).parent.rglob("*")
                       if p.is_file() and "__pycache__" not in p.parts}
    source = REPO / "src" / "vtgen"
    data = {p.relative_to(source) for p in source.rglob("*")
            if p.is_file() and "__pycache__" not in p.parts and p.suffix not in (".py", ".pyc")}
    missing = sorted(map(str, data - installed_files))
    assert not missing, f"files of src/vtgen not installed (add them to [tool.setuptools.package-data]): {missing}"
    print(f"\npackaging: venv, build and install took {installed[3]:.1f} s")


@pytest.mark.e2e
def test_installed_command_runs_outside_the_repo(installed):
    result = run_in(installed, str(installed[0] / "bin" / "vtgen"), "--help")
    assert result.returncode == 0, result.stderr
    assert "classify" in result.stdout and "Visual-tactile" in result.stdout


@pytest.mark.e2e
def test_installed_package_validates_params_and_names_a_typo(installed):
    python = str(installed[0] / "bin" / "python")
    good = run_in(installed, python, "-c", f"from vtgen.io.params import load_params; load_params({str(REPO / 'params.yaml')!r})")
    assert good.returncode == 0, good.stderr
    typo = typo_params(installed[2])
    bad = run_in(installed, python, "-c", f"from vtgen.io.params import load_params; load_params({str(typo)!r})")
    assert bad.returncode == 1 and "ParamsError" in bad.stderr
    assert "classify: unknown key 'lrr' (allowed: " in bad.stderr


@pytest.mark.e2e
def test_installed_command_vtgen_debug_switches_the_traceback(installed):
    vtgen, env = str(installed[0] / "bin" / "vtgen"), installed[1]
    typo = str(typo_params(installed[2]))
    env["VTGEN_DEBUG"] = "0"
    try:
        quiet = run_in(installed, vtgen, *FAILING, "--params", typo)
        env["VTGEN_DEBUG"] = "1"
        loud = run_in(installed, vtgen, *FAILING, "--params", typo)
    finally:
        env.pop("VTGEN_DEBUG")
    assert quiet.returncode == 2 and quiet.stderr.startswith(f"vtgen classify: error: {typo} is invalid:")
    assert "classify: unknown key 'lrr'" in quiet.stderr and "Traceback" not in quiet.stderr
    assert loud.returncode == 1 and loud.stderr.startswith("Traceback (most recent call last):")
    assert "vtgen.io.params.ParamsError:" in loud.stderr and "classify: unknown key 'lrr'" in loud.stderr
    assert str(installed[0]) in loud.stderr  # the traceback runs through the installed files


@pytest.mark.parametrize("stage", ["render", "ingest", "roi", "pairs", "settings", "report"])
def test_stages_without_networks_start_without_torch_or_scikit_learn(stage):
    """Each stage is a process of its own, many per run: the ones that only read and write images and tables
    must not pay torch's import (about a second) or scikit-learn's (another)."""
    code = (f"import sys, vtgen.cli, vtgen.stages.{stage}; "
            "print(sorted(m for m in ('torch', 'sklearn') if m in sys.modules))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]", f"vtgen.stages.{stage} imports {loaded}"
