import copy
import re
import subprocess
import sys

import pytest
import yaml

from vtgen.io.params import load_params, ParamsError, validate_params


def test_default_params_are_valid(default_params):
    assert validate_params(default_params) is default_params


def test_unknown_key_is_named(default_params):
    params = copy.deepcopy(default_params)
    params["roi"]["sise"] = 64
    with pytest.raises(ParamsError, match=r"roi: unknown key 'sise'"):
        validate_params(params)


def test_unknown_section_is_named(default_params):
    params = copy.deepcopy(default_params)
    params["trainnig"] = {}
    with pytest.raises(ParamsError, match=r"<top level>: unknown key 'trainnig'"):
        validate_params(params)


def test_wrong_type_is_named(default_params):
    params = copy.deepcopy(default_params)
    params["synthetic"]["samples_per_class"] = "sixty"
    with pytest.raises(ParamsError, match=r"synthetic\.samples_per_class: 'sixty' is not of type 'integer'"):
        validate_params(params)


@pytest.mark.parametrize("edit, message", [
    (lambda r1: r1.update(v2t="twelve"), r"translation\.class_gan\.r1\.v2t: 'twelve' is not of type 'number'"),
    (lambda r1: r1.pop("v2t"), r"translation\.class_gan\.r1: 'v2t' is a required property"),
    (lambda r1: r1.update(v2x=1), r"translation\.class_gan\.r1: unknown key 'v2x'"),
])
def test_a_value_given_per_direction_is_refused_naming_the_direction(default_params, edit, message):
    """A key that takes one value or {v2t: x, t2v: x}: the message names the direction at fault, not only that
    the mapping fits none of the forms."""
    params = copy.deepcopy(default_params)
    params["translation"]["class_gan"]["r1"] = {"v2t": 1, "t2v": 240}
    edit(params["translation"]["class_gan"]["r1"])
    with pytest.raises(ParamsError, match=message):
        validate_params(params)


def test_missing_key_is_named(default_params):
    params = copy.deepcopy(default_params)
    del params["pairing"]["seed"]
    with pytest.raises(ParamsError, match=r"pairing: 'seed' is a required property"):
        validate_params(params)


def test_synthetic_source_requires_render_path(default_params):
    params = copy.deepcopy(default_params)
    params["dataset"]["path"] = "elsewhere"
    with pytest.raises(ParamsError, match="dataset.path: must be 'data/raw/synthetic'"):
        validate_params(params)


def test_load_params_reports_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(ParamsError, match="no such params file"):
        load_params(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("roi: [unclosed\n")
    with pytest.raises(ParamsError, match="not valid YAML"):
        load_params(bad)


@pytest.mark.slow
def test_cli_stops_at_start_naming_the_key(tmp_path, default_params):
    params = copy.deepcopy(default_params)
    params["roi"]["size"] = "big"
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    result = subprocess.run([sys.executable, "-m", "vtgen", "ingest", "--params", str(path), "--out", str(tmp_path / "out")],
                            capture_output=True, text=True)
    assert result.returncode == 2
    assert "roi.size: 'big' is not of type 'integer'" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("key, value", [("pairing.val_fraction", float("nan")), ("presets.fast.lr", float("inf")),
                                        ("classify.low_data_fraction", float("nan"))])
def test_non_finite_numbers_are_refused_with_their_key(default_params, key, value):
    section, *rest = key.split(".")
    target = default_params[section]
    for part in rest[:-1]:
        target = target[part]
    target[rest[-1]] = value
    with pytest.raises(ParamsError, match=re.escape(key) + ".*not a finite number"):
        validate_params(default_params)
