"""Report stage: paper-shaped tables, metrics.json, and the page as a browser renders it."""

import json
import os
import shutil

import numpy as np
import pandas as pd
import pytest

from conftest import REPO
from vtgen.stages.report import accuracy_table, markdown_table, PAPER, ssim_tables

pytestmark = pytest.mark.e2e
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SCREENSHOT = REPO / "logs" / "test-artifacts" / "report.png"


def _by_class(aligned: bool) -> pd.DataFrame:
    rows = []
    for cls in ("denim", "felt", "(all)"):
        for candidate, scope, value in (("generated", "all", 0.6), ("real_train", "-", 0.3),
                                        ("nearest_neighbour", "-", 0.4), ("mean_image", "-", 0.45),
                                        ("flat_mean_colour", "-", 0.5)):
            rows.append({"direction": "v2t", "scope": scope, "candidate": candidate, "class": cls,
                         "colour_ssim": value + 0.1 if aligned and candidate != "real_train" else np.nan,
                         "grey_ssim": 0.7 if aligned else np.nan, "psnr": 20.0 if aligned else np.nan,
                         "ms_ssim": np.nan, "set_colour_ssim": value, "nearest_real_colour_ssim": value + 0.2,
                         "images": 3})
    return pd.DataFrame(rows)


def test_ssim_tables_put_reference_levels_and_the_paper_beside_ours():
    set_table, aligned = ssim_tables(_by_class(aligned=True), "v2t")
    assert list(set_table["class"]) == ["denim", "felt", "(all)"]
    assert list(set_table.columns) == ["class", "generated", "generated, nearest real", "real vs real",
                                       "nearest neighbour", "mean image", "flat mean colour", "paper"]
    assert set_table["real vs real"].tolist() == [0.3, 0.3, 0.3]
    assert set_table["paper"].iloc[-1] == PAPER["colour_ssim"]["v2t"] and set_table["paper"].iloc[0] == ""
    assert "MS-SSIM" not in aligned.columns  # never computed at this size: no empty column
    assert aligned["Colour-SSIM"].tolist() == pytest.approx([0.7] * 3)
    # unaligned data: no aligned table at all
    assert ssim_tables(_by_class(aligned=False), "v2t")[1] is None


def test_accuracy_table_reports_mean_and_spread_per_epoch():
    rows = [{"modality": "tactile", "setting": setting, "seed": seed, "epoch": epoch,
             "test_accuracy": base + 0.1 * epoch + 0.02 * seed,
             "gan_test_accuracy": 0.5 if setting == "real" else np.nan}
            for setting, base in (("real", 0.5), ("real+generated", 0.6)) for seed in (0, 1) for epoch in (1, 2)]
    table = accuracy_table(pd.DataFrame(rows), "tactile")
    assert table["real"].tolist() == ["0.610 ± 0.014", "0.710 ± 0.014"]
    assert table["real+generated"].iloc[1] == "0.810 ± 0.014"
    assert table["GAN-test (real-only classifier on generated)"].iloc[0] == "0.500 ± 0.000"
    assert table["paper"].tolist() == ["", PAPER["accuracy"]["tactile"]]
    assert markdown_table(table).splitlines()[0].startswith("| epoch | real | real+generated |")


def test_report_of_a_finished_run_has_every_section_and_metric(snakemake_project):
    project, _ = snakemake_project
    reports = project / "reports"
    metrics = json.loads((reports / "metrics.json").read_text())
    assert metrics["synthetic"] is True
    for direction in ("v2t", "t2v"):
        levels = metrics["ssim"][direction]
        for key in ("generated_set", "generated_aligned", "real_train_set", "flat_mean_colour_set",
                    "mean_image_set", "nearest_neighbour_set"):
            assert 0 <= levels[key] <= 1, key
    for modality in ("visual", "tactile"):
        assert set(metrics["classify"][modality]) >= {"real", "real+generated", "gan_test"}
    assert {"train_v2t_all", "classify_tactile", "score"} <= set(metrics["seconds"])
    figures = {p.name for p in (reports / "figures").glob("*.png")}
    assert figures == {"losses.png", "scores.png", "grid_v2t.png", "grid_t2v.png", "classification.png",
                       "timings.png"}
    summary = (reports / "summary.md").read_text()
    for heading in ("Data provenance", "Table I:", "Table II:", "Table III (visual)", "Table III (tactile)",
                    "Stage timings", "SYNTHETIC"):
        assert heading in summary, heading
    assert not list(reports.glob(".*tmp*"))  # the build folder is gone


@pytest.mark.skipif(CHROMIUM is None and not os.environ.get("CI"),
                    reason="chromium not installed (`make test` installs Debian's package with apt-get)")
def test_report_renders_in_headless_chromium_with_every_image_and_table(snakemake_project):
    """Open reports/index.html from disk; nothing may come from the network; save a screenshot artefact."""
    from playwright.sync_api import sync_playwright

    project, _ = snakemake_project
    index = project / "reports" / "index.html"
    SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--no-first-run"])
        page = browser.new_page(viewport={"width": 1200, "height": 900})
        requests, errors = [], []
        page.on("request", lambda request: requests.append(request.url))
        page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
        page.goto(index.as_uri(), wait_until="load")
        images = page.evaluate("() => Array.from(document.images).map(i => [i.getAttribute('src'), i.complete, "
                               "i.naturalWidth, i.naturalHeight])")
        captions = page.evaluate("() => Array.from(document.querySelectorAll('table caption')).map(c => c.textContent)")
        rows = page.evaluate("() => Array.from(document.querySelectorAll('table')).map(t => t.rows.length)")
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        browser.close()
    assert len(images) == 6
    for src, complete, width, height in images:
        assert complete and width > 0 and height > 0, src
    assert all(url.startswith("file://") for url in requests), [u for u in requests if not u.startswith("file://")]
    assert not errors, errors
    for prefix in ("Table I:", "Table II:", "Table III (visual)", "Table III (tactile)", "Trained generators"):
        assert any(c.startswith(prefix) for c in captions), prefix
    assert min(rows) >= 2  # a header and at least one row each
    assert SCREENSHOT.stat().st_size > 10_000
