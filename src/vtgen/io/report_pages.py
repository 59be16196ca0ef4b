"""Rendering of the report pages: the paper's reference values, tables as template data, and one helper
that renders a page from the Jinja2 templates in ``vtgen/io/templates`` as HTML (autoescaped) and Markdown.

Both reports (the run's report and the studies report) extend ``base.html`` / ``base.md`` and share
``style.css`` and the table and figure macros. Prose used by both formats of a page lives in a plain-text
macro file (``report_text.txt``, ``studies_text.txt``); HTML templates pass its output through the
``plaintext`` filter so that it is escaped.
"""

from __future__ import annotations

import errno
import json
import math
from functools import lru_cache
from pathlib import Path

import jinja2
import numpy as np
import yaml

TEMPLATES = Path(__file__).resolve().parent / "templates"

PAPER_FILE = Path(__file__).resolve().parent / "paper.yaml"
PAPER_ROWS = {"cloth_types": "cloth types", "network_parameters": "network parameters",
              "roi_with_noise": "ROI with noise", "roi_no_noise": "ROI without noise",
              "paired_dataset": "paired dataset"}


def load_paper(path: str | Path = PAPER_FILE) -> dict:
    """The paper's Tables I-III as printed (``paper.yaml``), plus views for the pages: ``colour_ssim``
    ({direction: {row: value}}), ``accuracy`` ({modality: {setting: {iteration: value}}}) and ``note``."""
    raw = yaml.safe_load(Path(path).read_text())
    table = raw["table_3_classification_accuracy"]
    columns = table["columns"]
    accuracy: dict = {"visual": {"real": {}, "real+generated": {}}, "tactile": {"real": {}, "real+generated": {}}}
    for row in table["rows"]:
        values = dict(zip(columns, row))
        for modality in accuracy:
            accuracy[modality]["real"][int(values["iteration"])] = values[f"{modality}_real"]
            accuracy[modality]["real+generated"][int(values["iteration"])] = values[f"{modality}_real_plus_generated"]
    return {**raw, "note": "values of Tables I-III as printed; " + raw["caveat"][:1].lower() + raw["caveat"][1:],
            "colour_ssim": {"v2t": dict(raw["table_1_v2t_colour_ssim"]), "t2v": dict(raw["table_2_t2v_colour_ssim"])},
            "accuracy": accuracy}


PAPER = load_paper()


def fmt(value, digits: int = 3) -> str:
    """A table cell as text: floats with ``digits`` decimals, None and NaN as an em dash, infinities by name."""
    if value is None:
        return "—"
    if isinstance(value, (float, np.floating)):
        if math.isnan(value):
            return "—"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return f"{value:.{digits}f}"
    return str(value)


def interval_cell(value, low=None, high=None, digits: int = 3) -> str:
    """``value [low, high]`` as text; the value alone when the interval is unknown, an em dash for no value."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "—"
    text = fmt(float(value), digits)
    if low is None or high is None or any(isinstance(v, float) and math.isnan(v) for v in (low, high)):
        return text
    return f"{text} [{fmt(float(low), digits)}, {fmt(float(high), digits)}]"


def overlap(a: tuple, b: tuple) -> bool | None:
    """True when the intervals ``a`` and ``b`` (low, high) overlap, None when either is unknown."""
    values = [v for v in (*a, *b)]
    if any(v is None or (isinstance(v, float) and math.isnan(v)) for v in values):
        return None
    return a[0] <= b[1] and b[0] <= a[1]


def md_cell(text) -> str:
    """Text safe inside a Markdown table cell (pipes escaped, line breaks flattened)."""
    return str(text).replace("|", "\\|").replace("\n", " ")


def plaintext(text) -> str:
    """``text`` as a plain string, so that the HTML page escapes it: a macro of a plain-text template
    (``*_text.txt``) called from an HTML template comes back marked safe without having escaped anything."""
    return str.__str__(text)


def lines(text) -> list[str]:
    """The non-blank lines of ``text``, stripped: a template macro's list items, one per line."""
    return [line.strip() for line in plaintext(text).splitlines() if line.strip()]


def plain(value):
    """``value`` with numpy scalars turned into Python ones (for templates and JSON)."""
    return value.item() if isinstance(value, np.generic) else value


def table_view(table, caption: str) -> dict:
    """A DataFrame as template data: ``{"caption", "columns", "rows"}`` with plain Python cell values."""
    return {"caption": caption, "columns": [str(c) for c in table.columns],
            "rows": [[plain(v) for v in row] for row in table.itertuples(index=False)]}


@lru_cache(maxsize=1)
def environment() -> jinja2.Environment:
    """The Jinja2 environment of the report templates: ``*.html`` autoescaped, undefined names an error."""
    env = jinja2.Environment(loader=jinja2.FileSystemLoader(str(TEMPLATES)),
                             autoescape=jinja2.select_autoescape(["html"], default_for_string=False, default=False),
                             undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True,
                             keep_trailing_newline=True)
    env.filters["fmt"] = fmt
    env.filters["md_cell"] = md_cell
    env.filters["lines"] = lines
    env.filters["plaintext"] = plaintext
    env.globals["paper"] = PAPER
    return env


def md_text(value) -> str:
    """A value as Markdown text that cannot open an HTML tag (``<`` and ``>`` as entities), so a class or
    file name such as ``<img src=x onerror=...>`` is shown, never run, where the Markdown is rendered."""
    return str(value).replace("<", "&lt;").replace(">", "&gt;")


@lru_cache(maxsize=1)
def markdown_environment() -> jinja2.Environment:
    """The environment of the ``*.md`` templates: every ``{{ value }}`` passes through :func:`md_text` (the
    templates' own literal HTML, such as ``<details>``, is kept)."""
    env = environment().overlay(finalize=md_text)
    return env


def render_page(name: str, context: dict) -> tuple[str, str]:
    """Render ``templates/<name>.html`` and ``templates/<name>.md`` with ``context``; return (html, markdown)."""
    return (environment().get_template(f"{name}.html").render(context),
            markdown_environment().get_template(f"{name}.md").render(context))


def read_json(path: str | Path) -> dict:
    """A JSON file written by an earlier stage; a missing or unreadable file is an error naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(errno.ENOENT, "no such file (an input of this report)", str(path))
    try:
        return json.loads(path.read_text())
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: not a readable JSON file: {exc}") from exc


def write_json(path: str | Path, data: dict) -> None:
    """Write ``data`` as JSON with sorted keys (byte-identical for identical data); NaN is refused."""
    try:
        text = json.dumps(data, indent=2, sort_keys=True, allow_nan=False)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    Path(path).write_text(text + "\n")
