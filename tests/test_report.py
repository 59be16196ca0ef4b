"""Report stage: paper-shaped tables, metrics.json, timings, training plot data, and the pages.

Fast tests run ``run_report`` on small fake stage outputs built in ``tmp_path`` (the files each stage
writes, with the columns of ``vtgen.io.tables``); the e2e tests read the report of the tiny pipeline.
"""

import json
import os
import shutil
import sys

import numpy as np
import pandas as pd
import pytest

from conftest import REPO, tiny_params, write_image
from vtgen.io.report_pages import PAPER, render_page
from vtgen.stages.report import accuracy_table, run_report, ssim_tables

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SCREENSHOT = REPO / "logs" / "test-artifacts" / "report.png"
CLASSES = ("<b>", "denim")
FOLDERS = ("ingest", "pairs", "models", "generated", "scores", "classify")


def _by_class(aligned: bool, classes=("denim", "felt")) -> pd.DataFrame:
    rows = []
    for direction in ("v2t", "t2v"):
        for cls in (*classes, "(all)"):
            for candidate, scope, value in (("generated", "all", 0.6), ("real_train", "-", 0.3),
                                            ("nearest_neighbour", "-", 0.4), ("mean_image", "-", 0.45),
                                            ("flat_mean_colour", "-", 0.5)):
                rows.append({"direction": direction, "scope": scope, "candidate": candidate, "class": cls,
                             "colour_ssim": value + 0.1 if aligned and candidate != "real_train" else np.nan,
                             "grey_ssim": 0.7 if aligned else np.nan, "psnr": 20.0 if aligned else np.nan,
                             "ms_ssim": np.nan, "set_colour_ssim": value, "nearest_real_colour_ssim": value + 0.2,
                             "images": 3 if cls != "(all)" else 3 * len(classes)})
    return pd.DataFrame(rows)


def _accuracy(modality: str) -> pd.DataFrame:
    rows = [{"modality": modality, "setting": setting, "seed": seed, "epoch": epoch,
             "test_accuracy": base + 0.1 * epoch + 0.02 * seed,
             "gan_test_accuracy": 0.5 if setting == "real" else np.nan, "train_images": 10, "real_images": 10,
             "generated_images": 0, "seconds": 1.0}
            for setting, base in (("real", 0.5), ("real+generated", 0.6)) for seed in (0, 1) for epoch in (1, 2)]
    return pd.DataFrame(rows)


def _write_json(path, data) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data))


def _timing(folder, stage: str, seconds: float) -> None:
    _write_json(folder / "timing.json", {"stage": stage, "seconds": seconds, "finished": "2024-01-01T00:00:00"})


def fake_run(root, at_chance: bool | None = None) -> dict:
    """The output folders of every stage the report reads, small and fake, under ``root``; return them."""
    folders = {name: root / name for name in FOLDERS}
    _write_json(folders["ingest"] / "summary.json", {"entries_in": 13, "kept": 12, "quarantined": 1, "with_note": 0,
                                                     "classes": list(CLASSES), "synthetic": True})
    pd.DataFrame([{"path": "x.png", "class": "denim", "modality": "visual", "reason": "truncated"}]).to_parquet(
        folders["ingest"] / "quarantine.parquet")
    _timing(folders["ingest"], "ingest", 1.5)
    _write_json(folders["pairs"] / "summary.json", {
        "tiles_per_split": {"test/visual": 2, "train/visual": 8},
        "v2t": {"train": {"pairs": 8, "aligned": 8}, "test": {"pairs": 2, "aligned": 2}},
        "t2v": {"train": {"pairs": 8, "aligned": 8}, "test": {"pairs": 2, "aligned": 2}}, "warnings": []})
    for direction, seconds in (("v2t", 4.0), ("t2v", 5.0)):
        model = folders["models"] / direction / "all"
        _write_json(model / "train.json", {"direction": direction, "scope": "all", "preset": "fast",
                                           "settings": {"size": 32}, "steps": 4, "wall_seconds": seconds,
                                           "seconds_per_iteration": seconds / 4, "final_val_l1": 0.2,
                                           "device": "cpu", "precision": "fp32"})
        metrics = model / "dvclive" / "plots" / "metrics"
        for name, values in (("loss_d", [0.7, 0.6]), ("loss_g_gan", [0.8, 0.9]), ("loss_g_l1", [0.5, 0.4]),
                             ("images_per_s", [50.0, 60.0])):
            (metrics / "train").mkdir(parents=True, exist_ok=True)
            pd.DataFrame({"step": [2, 4], name: values}).to_csv(metrics / "train" / f"{name}.tsv", sep="\t", index=False)
        (metrics / "val").mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"step": [4], "l1": [0.3]}).to_csv(metrics / "val" / "l1.tsv", sep="\t", index=False)
        _timing(model, "train", seconds)
        generated = folders["generated"] / direction
        _write_json(generated / "summary.json", {"direction": direction, "scopes": {"all": {"train": 2, "test": 2}}})
        write_image(generated / "preview.png", np.full((24, 48, 3), 128, np.uint8))
        _timing(generated, "generate", 0.5)
    _write_json(folders["scores"] / "summary.json", {"ms_ssim": "not computed: images are 32 px"})
    _by_class(aligned=True, classes=CLASSES).to_parquet(folders["scores"] / "by_class.parquet")
    _timing(folders["scores"], "score", 2.0)
    for modality in ("visual", "tactile"):
        settings = {"real": {"final_mean": 0.7}, "real+generated": {"final_mean": 0.8}}
        if at_chance is not None:
            settings["real"]["at_chance"] = at_chance
        _write_json(folders["classify"] / modality / "summary.json", {
            "modality": modality, "status": "ok", "classes": list(CLASSES), "settings": settings,
            "counts": {"real_test": 4}, "notes": []})
        _accuracy(modality).to_parquet(folders["classify"] / modality / "accuracy.parquet")
        _timing(folders["classify"] / modality, "classify", 3.0)
    return folders


def report(folders: dict, out) -> dict:
    return run_report(tiny_params(), *(folders[name] for name in FOLDERS), out)


def numbers(tree) -> list:
    """Every leaf of a nested dict."""
    return [leaf for value in tree.values() for leaf in (numbers(value) if isinstance(value, dict) else [value])]


# ---------------------------------------------------------------- tables


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
    table = accuracy_table(_accuracy("tactile"), "tactile")
    assert table["real"].tolist() == ["0.610 ± 0.014", "0.710 ± 0.014"]
    assert table["real+generated"].iloc[1] == "0.810 ± 0.014"
    assert table["GAN-test (real-only classifier on generated)"].iloc[0] == "0.500 ± 0.000"
    assert table["paper"].tolist() == ["", PAPER["accuracy"]["tactile"]]


def test_page_helper_autoescapes_html_but_not_markdown():
    table = {"caption": "a | b", "columns": ["class", "x"], "rows": [["<b>", 0.12345], ["felt", None]]}
    chance = {"modality": "<m>", "at_chance": ["real"], "classes": 2, "table": None, "status": "ok", "notes": []}
    context = {"title": "t", "synthetic": False} | _minimal_context(table) | {"classify": [chance]}
    page, summary = render_page("report", context)
    assert "<td>&lt;b&gt;</td><td>0.123</td>" in page and "<td>—</td>" in page
    assert "warning: the &lt;m&gt; classifier ends at chance level" in page and "<m>" not in page
    assert "| class | x |" in summary and "| <b> | 0.123 |" in summary


def _minimal_context(table: dict) -> dict:
    run = {"code_version": "c", "built": "b", "python": "3", "torch": "2", "cpus": 1, "preset": "fast", "scope": ["all"]}
    return {"dataset": {"source": "s", "path": "p"}, "ingest": {}, "pairs": {}, "run": run, "params_yaml": "",
            "directions": ["v2t"], "figures": {"losses": False, "scores": False, "grid_v2t": False,
                                               "classification": False},
            "quarantine": None, "models": table, "ms_ssim_note": None, "ssim": [], "classify": [], "timings": None}


# ---------------------------------------------------------------- the stage on fake inputs


@pytest.mark.slow
def test_metrics_json_holds_headline_numbers_and_is_byte_identical_across_runs(tmp_path):
    folders = fake_run(tmp_path / "in")
    first = report(folders, tmp_path / "one")
    report(folders, tmp_path / "two")
    text = (tmp_path / "one" / "metrics.json").read_bytes()
    assert text == (tmp_path / "two" / "metrics.json").read_bytes()
    metrics = json.loads(text)
    assert metrics == first
    assert list(metrics) == sorted(metrics)
    leaves = numbers(metrics)
    assert leaves and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in leaves)
    assert metrics["v2t"] == pytest.approx({
        "set_colour_ssim": 0.6, "aligned_colour_ssim": 0.7, "nearest_real_colour_ssim": 0.8, "test_images": 6,
        "real_vs_real": 0.3, "nearest_neighbour": 0.4, "nearest_neighbour_aligned": 0.5, "mean_image": 0.45,
        "mean_image_aligned": 0.55, "flat_mean_colour": 0.5, "flat_mean_colour_aligned": 0.6})
    # final epoch (2), mean over seeds 0 and 1: 0.5 + 0.2 + 0.01
    assert metrics["classify"]["tactile"] == pytest.approx(
        {"real": 0.71, "real+generated": 0.81, "gan_test": 0.5, "seeds": 2, "real_test_images": 4})
    assert metrics["counts"] == {"classes": 2, "images_kept": 12, "quarantined": 1, "models": 2}


@pytest.mark.slow
def test_report_reads_only_its_arguments(tmp_path, monkeypatch):
    """Inputs under unusual names, run from an empty folder: every file opened under tmp_path is an input or output."""
    folders = fake_run(tmp_path / "elsewhere")
    empty = tmp_path / "cwd"
    empty.mkdir()
    monkeypatch.chdir(empty)
    opened = _record_opens()
    try:
        report(folders, tmp_path / "out")
    finally:
        _stop_recording()
    assert not (empty / "data").exists() and not any(empty.iterdir())  # nothing read or written beside the cwd
    inside = [p for p in opened if p.startswith(str(tmp_path))]
    assert inside, "the audit hook saw no file being opened"
    allowed = (str(tmp_path / "elsewhere"), str(tmp_path / "out"))
    assert all(p.startswith(allowed) for p in inside), [p for p in inside if not p.startswith(allowed)]
    assert (tmp_path / "out" / "index.html").is_file() and (tmp_path / "out" / "plots" / "training.csv").is_file()


_OPENED: list[str] | None = None


def _audit(event: str, args) -> None:
    if _OPENED is not None and event == "open" and isinstance(args[0], (str, os.PathLike)):
        _OPENED.append(os.path.abspath(os.fspath(args[0])))


def _record_opens() -> list[str]:
    global _OPENED
    if not getattr(sys, "_vtgen_report_hook", False):
        sys.addaudithook(_audit)  # hooks cannot be removed: install once, record only between these calls
        sys._vtgen_report_hook = True
    _OPENED = []
    return _OPENED


def _stop_recording() -> None:
    global _OPENED
    _OPENED = None


@pytest.mark.slow
def test_html_escapes_a_class_name_and_shows_every_section(tmp_path):
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in"), out)
    page = (out / "index.html").read_text()
    assert "<td>&lt;b&gt;</td>" in page and "<td><b></td>" not in page
    assert "classes: 2 (&lt;b&gt;, denim)" in page
    summary = (out / "summary.md").read_text()
    for heading in ("Data provenance", "Table I:", "Table II:", "Table III (visual)", "Table III (tactile)",
                    "Stage timings", "SYNTHETIC", "studies/index.html", "MS-SSIM not computed", "Quarantined inputs (1"):
        assert heading in summary and heading in page, heading
    assert "chance level" not in page  # classify gave no at_chance mark: no warning
    figures = {p.name for p in (out / "figures").glob("*.png")}
    assert figures == {"losses.png", "scores.png", "grid_v2t.png", "grid_t2v.png", "classification.png",
                       "timings.png"}
    assert page.count("<img ") == 6 and not list(out.glob(".*tmp*"))


@pytest.mark.parametrize("flag", [True, False])
@pytest.mark.slow
def test_a_classifier_at_chance_level_is_warned_about_only_when_marked(tmp_path, flag):
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in", at_chance=flag), out)
    page, summary = (out / "index.html").read_text(), (out / "summary.md").read_text()
    assert ('<p class="warning">warning: the tactile classifier ends at chance level (2 classes) in: real;' in page) is flag
    assert ("visual classifier ends at chance level" in summary) is flag


@pytest.mark.slow
def test_timings_and_training_plot_data_come_from_the_input_folders(tmp_path):
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in"), out)
    timings = json.loads((out / "timings.json").read_text())
    assert [j["job"] for j in timings["jobs"]] == [
        "ingest", "train_v2t_all", "train_t2v_all", "generate_v2t", "generate_t2v", "score", "classify_visual",
        "classify_tactile"]  # the fake pairs folder has no timing.json: left out
    assert timings["jobs"][1] == {"job": "train_v2t_all", "stage": "train", "seconds": 4.0,
                                  "finished": "2024-01-01T00:00:00"}
    assert timings["total_seconds"] == pytest.approx(1.5 + 4 + 5 + 0.5 + 0.5 + 2 + 3 + 3)
    training = pd.read_csv(out / "plots" / "training.csv")
    assert list(training.columns) == ["step", "model", "loss_d", "loss_g_gan", "loss_g_l1", "val_l1"]
    assert training["model"].tolist() == ["t2v/all", "t2v/all", "v2t/all", "v2t/all"]
    assert training["loss_g_l1"].tolist() == [0.5, 0.4, 0.5, 0.4]
    assert training["val_l1"].isna().tolist() == [True, False, True, False]


def test_a_missing_input_is_an_error_naming_the_file(tmp_path):
    folders = fake_run(tmp_path / "in")
    (folders["scores"] / "by_class.parquet").unlink()
    with pytest.raises(FileNotFoundError) as error:
        report(folders, tmp_path / "out")
    assert error.value.filename == str(folders["scores"] / "by_class.parquet")
    (folders["ingest"] / "summary.json").write_text("{not json")
    with pytest.raises(ValueError, match="summary.json: not a readable JSON file"):
        report(folders, tmp_path / "out")


# ---------------------------------------------------------------- the studies report


def fake_studies(root) -> tuple[dict, tuple]:
    """params with one standard and one per-class experiment, and the three folders the studies report reads."""
    params = tiny_params()
    runs = params["studies"]["experiments"]["runs"]
    params["studies"]["experiments"]["runs"] = {"default": runs["default"], "cloth_types": runs["cloth_types"]}
    experiments, frontier, stability = root / "experiments", root / "frontier", root / "stability"
    for folder in (frontier, stability):
        folder.mkdir(parents=True)
    quality = pd.DataFrame([{"run": "run", "direction": "v2t", "class": c, "metric": "aligned", "quality": 0.6,
                             "real_train": 0.3, "nearest_neighbour": 0.4, "mean_image": 0.45, "flat_mean_colour": 0.5}
                            for c in (*CLASSES, "(all)")])
    for name, run in (("default", {"v2t": {"train_seconds": 10.0, "gan_test": 0.9},
                                   "t2v": {"train_seconds": 12.0, "gan_test": 0.8}}),
                      ("cloth_types", {"classes": {c: {"setting": "tiny", "train_seconds": 5.0, "gan_test": 0.7}
                                                   for c in CLASSES},
                                       "train_seconds": 10.0, "fixed_large": {"setting": "width_64",
                                                                               "train_seconds_estimate": 40.0}})):
        _write_json(experiments / name / "result.json", {"about": f"about <i>{name}</i>", "mode": runs[name]["mode"],
                                                         "runs": {"run": run}})
        quality.to_csv(experiments / name / "quality.csv", index=False)
    pd.DataFrame([{"setting": s, "overrides": "{}" if s == "centre" else '{"preset.ngf": 64}', "size": 32,
                   "seconds": sec, "seconds_std": 0.1, "quality": q, "quality_std": 0.01, "gan_test": 0.9,
                   "on_frontier": True, "is_default": s == "centre"}
                  for s, sec, q in (("centre", 10.0, 0.6), ("width_64", 20.0, 0.7))]).to_csv(
        frontier / "frontier.csv", index=False)
    write_image(frontier / "pareto.png", np.zeros((8, 8, 3), np.uint8))
    _write_json(frontier / "capacity.json", {"tolerance": 0.02, "large": "width_64", "seconds_auto": 30.0,
                                             "seconds_fixed_large": 40.0, "saved_fraction": 0.25,
                                             "classes": {c: {"setting": "centre", "seconds": 15.0} for c in CLASSES}})
    pd.DataFrame([{"case": "lr_huge", "outcome": "stopped", "message": "loss <NaN>"}]).to_csv(
        stability / "stability.csv", index=False)
    return params, (experiments, frontier, stability)


def test_studies_report_uses_the_shared_templates_and_escapes(tmp_path):
    from vtgen.io.provenance import code_files
    from vtgen.studies.report import run_studies_report

    params, folders = fake_studies(tmp_path / "in")
    out = tmp_path / "reports" / "studies"
    run_studies_report(params, *folders, out)
    page, summary = (out / "index.html").read_text(), (out / "summary.md").read_text()
    assert not any(path.match("stages/report.py") for path in code_files("vtgen.studies.report"))
    assert page.startswith("<!DOCTYPE html>") and "body{font-family" in page  # base.html with style.css
    assert '<a href="../index.html">main report</a>' in page and "SYNTHETIC DATA" in page
    assert "<td>&lt;b&gt;</td>" in page and "loss &lt;NaN&gt;" in page and "<td><b></td>" not in page
    assert "<p>about &lt;i&gt;default&lt;/i&gt;. Overrides:" in page and "<i>" not in page  # prose is escaped too
    assert "about <i>default</i>. Overrides:" in summary
    assert "30 s with capacity auto, against 40 s" in summary and "25% saved" in summary
    assert "Training time with capacity auto: 10 s for all 2 classes" in page  # per-class run vs 'width_64'
    assert "| cloth_types | v2t |" in summary and (out / "figures" / "pareto.png").is_file()


# ---------------------------------------------------------------- the tiny pipeline (slow)


@pytest.mark.e2e
def test_report_of_a_finished_run_has_every_section_and_metric(snakemake_project):
    project, _ = snakemake_project
    reports = project / "reports"
    metrics = json.loads((reports / "metrics.json").read_text())
    for direction in ("v2t", "t2v"):
        levels = metrics[direction]
        for key in ("set_colour_ssim", "aligned_colour_ssim", "real_vs_real", "flat_mean_colour", "mean_image",
                    "nearest_neighbour"):
            assert 0 <= levels[key] <= 1, key
    for modality in ("visual", "tactile"):
        assert set(metrics["classify"][modality]) >= {"real", "real+generated", "gan_test"}
    jobs = {j["job"] for j in json.loads((reports / "timings.json").read_text())["jobs"]}
    assert {"train_v2t_all", "classify_tactile", "score"} <= jobs
    figures = {p.name for p in (reports / "figures").glob("*.png")}
    assert figures == {"losses.png", "scores.png", "grid_v2t.png", "grid_t2v.png", "classification.png",
                       "timings.png"}
    summary = (reports / "summary.md").read_text()
    for heading in ("Data provenance", "Table I:", "Table II:", "Table III (visual)", "Table III (tactile)",
                    "Stage timings", "SYNTHETIC"):
        assert heading in summary, heading
    assert pd.read_csv(reports / "plots" / "training.csv")["loss_g_l1"].notna().any()
    assert not list(reports.glob(".*tmp*"))  # the build folder is gone


@pytest.mark.e2e
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
