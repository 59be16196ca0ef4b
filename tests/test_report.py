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
from vtgen.io.report_pages import PAPER, PAPER_FILE, load_paper, render_page
from vtgen.io.report_tables import accuracy_table, models_table, ssim_tables
from vtgen.stages.report import model_runs, run_report

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SCREENSHOT = REPO / "logs" / "test-artifacts" / "report.png"
CLASSES = ("<b>", "denim")
FOLDERS = ("ingest", "pairs", "models", "generated", "scores", "classify")
SHARED_PAPER = REPO.parent / "shared" / "paper" / "published_results.yaml"
INTERVAL_METRICS = ("colour_ssim", "grey_ssim", "psnr", "set_colour_ssim", "nearest_real_colour_ssim")


def _by_class(aligned: bool, classes=("denim", "felt"), half_width: float = 0.02) -> pd.DataFrame:
    """The score stage's by_class table: every mean with a 95% interval of +- ``half_width``."""
    rows = []
    for direction in ("v2t", "t2v"):
        for cls in (*classes, "(all)"):
            for candidate, scope, value in (("generated", "all", 0.6), ("real_train", "-", 0.3),
                                            ("nearest_neighbour", "-", 0.4), ("mean_image", "-", 0.45),
                                            ("flat_mean_colour", "-", 0.5)):
                row = {"direction": direction, "scope": scope, "candidate": candidate, "class": cls,
                       "colour_ssim": value + 0.1 if aligned and candidate != "real_train" else np.nan,
                       "grey_ssim": 0.7 if aligned else np.nan, "psnr": 20.0 if aligned else np.nan,
                       "ms_ssim": np.nan, "set_colour_ssim": value, "nearest_real_colour_ssim": value + 0.2,
                       "images": 3 if cls != "(all)" else 3 * len(classes), "groups": 2 if cls != "(all)" else 4}
                for metric in INTERVAL_METRICS:
                    row[f"{metric}_low"], row[f"{metric}_high"] = row[metric] - half_width, row[metric] + half_width
                rows.append(row)
    return pd.DataFrame(rows)


def _distribution(classes=("denim", "felt")) -> pd.DataFrame:
    """The score stage's distribution table: generated worse than real held-out, better than every baseline."""
    level = {"real_heldout": 0.01, "generated": 0.05, "nearest_neighbour": 0.2, "mean_image": 0.3,
             "flat_mean_colour": 0.4, "blurred_real": 0.25}
    rows = []
    for direction in ("v2t", "t2v"):
        for cls in (*classes, "(all)"):
            n = 3 if cls != "(all)" else 6
            for candidate, value in level.items():
                scope = "all" if candidate == "generated" else "-"
                for view, metric, number, interval in (
                        ("classifier", "kid", value, True), ("classifier", "fid", 100 * value, False),
                        ("classifier", "two_sample", 0.5 + value, True), ("classifier", "coverage", 1 - value, False),
                        ("random", "kid", value, True), ("pixels", "spectrum", value / 10, False)):
                    rows.append({"direction": direction, "scope": scope, "class": cls, "candidate": candidate,
                                 "view": view, "metric": metric, "value": number,
                                 "low": number - 0.005 if interval else np.nan,
                                 "high": number + 0.005 if interval else np.nan, "n": n, "n_reference": n})
    return pd.DataFrame(rows)


def _memorisation(classes=("denim", "felt")) -> pd.DataFrame:
    rows = []
    for direction in ("v2t", "t2v"):
        for cls in (*classes, "(all)"):
            for view in ("classifier", "pixels"):
                for candidate, rate in (("generated", 0.5 if direction == "t2v" else 0.1), ("real_heldout", 0.1)):
                    rows.append({"direction": direction, "class": cls, "view": view, "candidate": candidate,
                                 "rate": rate, "nearest_is_train_share": rate, "n": 60, "n_train": 80})
    return pd.DataFrame(rows)


def _nearest_training(folder) -> None:
    """The score stage's nearest-training table and picture strip: two V2T pairs of 8 px images, the first a
    flagged copy (distance 0), the second not flagged; T2V none."""
    rows = [{"direction": "v2t", "view": "classifier", "rank": rank, "generated_path": f"data/generated/v2t/{rank}.png",
             "train_path": f"data/roi/train/{rank}.png", "generated_class": "denim", "train_class": "denim",
             "distance": distance, "threshold": 0.5, "flagged": distance < 0.5} for rank, distance in enumerate((0.0, 0.7))]
    pd.DataFrame(rows).to_parquet(folder / "nearest_training.parquet")
    strip = np.zeros((16, 16, 3), np.uint8)
    strip[:, :8] = 200  # the copy: the same picture above and below
    write_image(folder / "nearest_training_v2t.png", strip)


def _verdicts() -> list[dict]:
    """Verdicts as the score stage writes them: V2T passes, T2V warns on memorisation."""
    found = []
    for direction in ("v2t", "t2v"):
        found.append({"direction": direction, "family": "KID (classifier)", "metric": "kid", "view": "classifier",
                      "status": "ok", "generated": 0.05, "real_heldout": 0.01, "best_baseline": "nearest_neighbour",
                      "best_baseline_value": 0.2, "position": 0.79, "n": 6, "n_real": 6,
                      "text": f"{direction.upper()} KID (classifier): generated 0.05 beats every trivial baseline "
                              f"beyond the intervals (best nearest_neighbour 0.2; real vs real 0.01; n = 6)"})
    found.append({"direction": "t2v", "family": "memorisation (classifier)", "metric": "memorisation",
                  "view": "classifier", "status": "warning", "generated": 0.5, "real_heldout": 0.1, "n": 60,
                  "n_real": 60, "text": "T2V memorisation (classifier): 0.500 of generated test images are closer to a "
                                        "training image than any held-out real image is (above the real held-out "
                                        "rate 0.100; n = 60 generated, 60 real)"})
    return found


def _pairs(direction: str, kinds: dict[str, int]) -> pd.DataFrame:
    rows = [{"direction": direction, "split": split, "class": "denim", "input_path": f"in{i}.png",
             "target_path": f"t{i}.png", "input_source": "s", "target_source": "s", "aligned": kind == "pixel",
             "pair_kind": kind}
            for split, count in (("train", 8), ("test", 2)) for kind, share in kinds.items()
            for i in range(int(count * share))]
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


def _timing(folder, stage: str, seconds: float, **own) -> None:
    """timing.json as the stage command writes it: the stage's ``own`` times, then its wall time and date."""
    _write_json(folder / "timing.json", {**own, "stage": stage, "seconds": seconds, "finished": "2024-01-01T00:00:00"})


def fake_run(root, at_chance: bool | None = None, greyscale: bool = False, half_width: float = 0.02) -> dict:
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
        "t2v": {"train": {"pairs": 8, "aligned": 4}, "test": {"pairs": 2, "aligned": 1}},
        "warnings": ["v2t: class denim: 2 name pairs promised by the layout were dropped"]})
    _pairs("v2t", {"pixel": 1.0}).to_parquet(folders["pairs"] / "v2t.parquet")
    _pairs("t2v", {"pixel": 0.5, "class": 0.5}).to_parquet(folders["pairs"] / "t2v.parquet")
    for direction, seconds in (("v2t", 4.0), ("t2v", 5.0)):
        model = folders["models"] / direction / "all"
        _write_json(model / "train.json", {"direction": direction, "scope": "all", "preset": "fast",
                                           "settings": {"size": 32}, "steps": 4, "final_val_l1": 0.2,
                                           "device": "cpu", "precision": "fp32"})
        metrics = model / "dvclive" / "plots" / "metrics"
        for name, values in (("loss_d", [0.7, 0.6]), ("loss_g_gan", [0.8, 0.9]), ("loss_g_l1", [0.5, 0.4])):
            (metrics / "train").mkdir(parents=True, exist_ok=True)
            pd.DataFrame({"step": [2, 4], name: values}).to_csv(metrics / "train" / f"{name}.tsv", sep="\t", index=False)
        (metrics / "val").mkdir(parents=True, exist_ok=True)
        pd.DataFrame({"step": [4], "l1": [0.3]}).to_csv(metrics / "val" / "l1.tsv", sep="\t", index=False)
        _timing(model, "train", seconds, wall_seconds=seconds - 0.5, seconds_per_iteration=(seconds - 0.5) / 4,
                resumed_from_step=0)
        generated = folders["generated"] / direction
        _write_json(generated / "summary.json", {"direction": direction, "scopes": {"all": {"train": 2, "test": 2}}})
        write_image(generated / "preview.png", np.full((24, 48, 3), 128, np.uint8))
        _timing(generated, "generate", 0.5)
    facts = {"halves_by": "group", "blur_sigma": 1.0, "half_a": 6, "half_b": 6, "greyscale": greyscale,
             "ssim_name": "SSIM" if greyscale else "Colour-SSIM"}
    _write_json(folders["scores"] / "summary.json", {
        "ms_ssim": "not computed: images are 32 px", "verdicts": _verdicts(), "not_scored": {}, "notes": [],
        "distribution": {"v2t": facts, "t2v": facts}, "seconds": {"ssim": 1.0}})
    _by_class(aligned=True, classes=CLASSES, half_width=half_width).to_parquet(folders["scores"] / "by_class.parquet")
    _distribution(CLASSES).to_parquet(folders["scores"] / "distribution.parquet")
    _memorisation(CLASSES).to_parquet(folders["scores"] / "memorisation.parquet")
    _nearest_training(folders["scores"])
    _timing(folders["scores"], "score", 2.0)
    for modality in ("visual", "tactile"):
        settings = {"real": {"final_mean": 0.71, "interval": [0.3, 0.95], "test_images": 4},
                    "real+generated": {"final_mean": 0.81, "interval": [0.4, 0.97], "test_images": 4},
                    "low-data real": {"final_mean": 0.45, "interval": [0.15, 0.8], "test_images": 4}}
        if at_chance is not None:
            settings["real"]["at_chance"] = at_chance
        _write_json(folders["classify"] / modality / "summary.json", {
            "modality": modality, "status": "ok", "classes": list(CLASSES), "settings": settings,
            "counts": {"real_test": 4}, "notes": [], "test_images_per_class": {c: 2 for c in CLASSES},
            "gan_test": {"setting": "real", "final_mean": 0.5, "images": 4, "interval": [0.15, 0.85]},
            "comparisons": [{"setting": "real+generated", "against": "real", "difference": 0.1, "overlap": True,
                             "paired_interval": [-0.05, 0.25], "within_noise": True,
                             "verdict": "within noise (the paired 95% interval includes 0)"}],
            "more_real_data": {"setting": "real", "against": "low-data real", "difference": 0.26,
                               "paired_interval": [-0.02, 0.54], "within_noise": True},
            "policy": _policy(modality),
            # real-only confusion on the 2 + 2 real test images (rows true class): tactile reads class 0 at 0.5
            "real_confusion": [[2, 0], [1, 1]] if modality == "visual" else [[1, 1], [0, 2]]})
        _accuracy(modality).to_parquet(folders["classify"] / modality / "accuracy.parquet")
        _classify_by_class(modality).to_parquet(folders["classify"] / modality / "by_class.parquet")
        _timing(folders["classify"] / modality, "classify", 3.0)
    return folders


def _policy(modality: str) -> dict:
    """summary.json's policy as the classify stage writes it: tactile chose real+generated on validation, visual
    had no validation split and stayed real only."""
    test = {"setting": "real", "accuracy": 0.71, "interval": [0.3, 0.95], "real_accuracy": 0.71,
            "real_interval": [0.3, 0.95], "images": 4, "gain": 0.0, "gain_interval": [0.0, 0.0]}
    if modality == "visual":
        return {"mode": "auto", "val_images": 0, "val_groups": 0, "chosen": "real", "uses_generated": False,
                "candidates": [], "test": test,
                "reason": "2 of 2 classes have no validation images (denim, <b>): the data has too few groups"}
    return {"mode": "auto", "val_images": 6, "val_groups": 6, "chosen": "real+generated", "uses_generated": True,
            "reason": "'real+generated' beat real only on the validation split by +0.300 accuracy, beyond its interval",
            "candidates": [{"setting": "real+generated", "val_accuracy": 0.9, "val_gain": 0.3,
                            "val_gain_interval": [0.1, 0.5], "ratio": 1.0, "filter": "all", "generated_images": [4, 4]}],
            "test": dict(test, setting="real+generated", accuracy=0.81, interval=[0.4, 0.97], gain=0.1,
                         gain_interval=[-0.05, 0.25])}


def _classify_by_class(modality: str) -> pd.DataFrame:
    rows = [{"modality": modality, "setting": setting, "class": cls, "images": 2 if cls != "(all)" else 4,
             "accuracy": value, "low": value - 0.3, "high": min(value + 0.2, 1.0), "seeds": 2}
            for setting, value in (("real", 0.71), ("real+generated", 0.81), ("GAN-test", 0.5))
            for cls in (*CLASSES, "(all)")]
    return pd.DataFrame(rows)


def fake_one_modality(root) -> dict:
    """The stage outputs of a tactile-only dataset: no pairs, no models, nothing scored, no visual classifier."""
    folders = {name: root / name for name in FOLDERS}
    reason = "translation needs both modalities: this dataset has tactile images only"
    _write_json(folders["ingest"] / "summary.json", {"entries_in": 12, "kept": 12, "quarantined": 0, "with_note": 0,
                                                     "classes": list(CLASSES), "modalities": ["tactile"],
                                                     "duplicates": {"exact_duplicate_files": 1, "near_duplicate_files": 3,
                                                                    "near_duplicate_rule": "16x16 thumbnails"},
                                                     "translation": {"possible": False, "reason": "no visual images"}})
    pd.DataFrame(columns=["path", "class", "modality", "reason"]).to_parquet(folders["ingest"] / "quarantine.parquet")
    _write_json(folders["pairs"] / "summary.json", {"tiles_per_split": {"test/tactile": 4, "train/tactile": 8},
                                                    "translation": {"possible": False, "reason": reason},
                                                    "warnings": []})
    for direction in ("v2t", "t2v"):
        _pairs(direction, {}).reindex(columns=["direction", "split", "class", "input_path", "target_path",
                                               "input_source", "target_source", "aligned", "pair_kind"]).to_parquet(
            folders["pairs"] / f"{direction}.parquet")
        _write_json(folders["models"] / direction / "all" / "train.json",
                    {"direction": direction, "scope": "all", "status": f"not applicable: {reason}"})
        _write_json(folders["generated"] / direction / "summary.json",
                    {"direction": direction, "scopes": {"all": {"status": f"not applicable: {reason}"}}})
    _write_json(folders["scores"] / "summary.json", {"verdicts": [], "distribution": {}, "notes": [],
                                                     "not_scored": {d: "no generated test images" for d in ("v2t", "t2v")}})
    pd.DataFrame(columns=["direction", "scope", "candidate", "class"]).to_parquet(folders["scores"] / "by_class.parquet")
    _distribution(CLASSES).iloc[:0].to_parquet(folders["scores"] / "distribution.parquet")
    _memorisation(CLASSES).iloc[:0].to_parquet(folders["scores"] / "memorisation.parquet")
    pd.DataFrame(columns=["direction", "view", "rank", "generated_path", "train_path", "generated_class", "train_class",
                          "distance", "threshold", "flagged"]).to_parquet(folders["scores"] / "nearest_training.parquet")
    visual = folders["classify"] / "visual"
    _write_json(visual / "summary.json", {"modality": "visual", "status": "not applicable: classification needs at "
                                          "least 2 classes, the data has 0", "classes": [], "notes": []})
    _accuracy("visual").iloc[:0].to_parquet(visual / "accuracy.parquet")
    _classify_by_class("visual").iloc[:0].to_parquet(visual / "by_class.parquet")
    tactile = folders["classify"] / "tactile"
    real_only = _accuracy("tactile")
    real_only = real_only[real_only["setting"] == "real"].assign(gan_test_accuracy=np.nan)
    _write_json(tactile / "summary.json", {
        "modality": "tactile", "status": "ok", "classes": list(CLASSES), "counts": {"real_test": 4},
        "settings": {"real": {"final_mean": 0.71, "interval": [0.3, 0.95], "test_images": 4}}, "gan_test": None,
        "comparisons": [], "test_images_per_class": {c: 2 for c in CLASSES},
        "notes": ["no generated test images of tactile: no GAN-test"]})
    real_only.to_parquet(tactile / "accuracy.parquet")
    by_class = _classify_by_class("tactile")
    by_class[by_class["setting"] == "real"].to_parquet(tactile / "by_class.parquet")
    return folders


def report(folders: dict, out) -> dict:
    return run_report(tiny_params(), *(folders[name] for name in FOLDERS), out)


def flat(tree: dict, prefix: str = "") -> dict:
    """A nested dict as {"a.b": leaf} (the columns dvc exp show makes of metrics.json)."""
    out = {}
    for key, value in tree.items():
        out |= flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value}
    return out


def numbers(tree) -> list:
    """Every leaf of a nested dict."""
    return [leaf for value in tree.values() for leaf in (numbers(value) if isinstance(value, dict) else [value])]


# ---------------------------------------------------------------- tables


def test_ssim_tables_put_n_intervals_and_reference_levels_beside_ours():
    set_table, aligned = ssim_tables(_by_class(aligned=True), "v2t")
    assert list(set_table["class"]) == ["denim", "felt", "(all)"]
    assert list(set_table.columns) == ["class", "n", "generated", "generated, nearest real",
                                       "generated vs best baseline", "n real", "real vs real", "nearest neighbour",
                                       "mean image", "flat mean colour"]
    assert set_table["n"].tolist() == [3, 3, 6]
    assert set_table["real vs real"].tolist() == ["0.300 [0.280, 0.320]"] * 3
    assert set_table["generated"].iloc[-1] == "0.600 [0.580, 0.620]"
    # 0.6 +- 0.02 against the flat colour's 0.5 +- 0.02: separated, so ranked
    assert set_table["generated vs best baseline"].tolist() == ["above flat mean colour"] * 3
    assert "MS-SSIM" not in aligned.columns  # never computed at this size: no empty column
    assert aligned["Colour-SSIM"].tolist() == ["0.700 [0.680, 0.720]"] * 3
    assert aligned["PSNR dB"].iloc[0] == "20.00 [19.98, 20.02]"
    # unaligned data: no aligned table at all
    assert ssim_tables(_by_class(aligned=False), "v2t")[1] is None


def test_overlapping_intervals_are_called_within_noise_not_ranked():
    set_table, _ = ssim_tables(_by_class(aligned=True, half_width=0.08), "v2t")
    assert set_table["generated vs best baseline"].tolist() == ["within noise of flat mean colour (intervals overlap)"] * 3
    no_interval = _by_class(aligned=False).drop(columns=[c for c in _by_class(False) if c.endswith(("_low", "_high"))])
    set_table, _ = ssim_tables(no_interval, "v2t")
    assert set_table["generated"].iloc[0] == "0.600" and set_table["generated vs best baseline"].iloc[0] == (
        "above flat mean colour (no interval)")


def test_greyscale_data_is_labelled_ssim_not_colour_ssim():
    set_table, aligned = ssim_tables(_by_class(aligned=True), "t2v", "SSIM")
    assert "SSIM" in aligned.columns and "Colour-SSIM" not in aligned.columns
    assert "grey SSIM" not in aligned.columns  # the same number on greyscale data
    assert "flat mean colour SSIM" in aligned.columns


def test_accuracy_table_reports_mean_spread_interval_and_the_paper_per_iteration():
    table = accuracy_table(_accuracy("tactile"), "tactile", test_images=4, gan_images=4)
    assert table["epoch / iteration"].tolist() == list(range(1, 11))  # our 2 epochs beside the paper's 10 iterations
    assert table["real"].iloc[0].startswith("0.610 ± 0.014 [") and table["real"].iloc[2] == ""
    assert table["real+generated"].iloc[1].startswith("0.810 ± 0.014 [")
    assert table["GAN-test (real-only classifier on generated)"].iloc[0].startswith("0.500 ± 0.000 [")
    assert table["paper real"].tolist()[:2] == ["0.7776", "0.8249"]
    assert table["paper real+generated"].iloc[-1] == "0.9058"
    assert accuracy_table(_accuracy("tactile"), "tactile")["real"].iloc[0] == "0.610 ± 0.014"  # no n: no interval


def test_paper_values_are_the_published_tables():
    assert PAPER["colour_ssim"]["v2t"] == {"cloth_types": 0.89717, "network_parameters": 0.90896,
                                           "roi_with_noise": 0.92059, "roi_no_noise": 0.91188,
                                           "paired_dataset": 0.90471}
    assert PAPER["colour_ssim"]["t2v"]["cloth_types"] == 0.77279
    assert PAPER["accuracy"]["visual"]["real"][10] == 0.9881 and PAPER["accuracy"]["tactile"]["real+generated"][1] == 0.8506
    assert "not state how generated and real images were matched" in PAPER["caveat"]
    assert PAPER_FILE.name == "paper.yaml" and PAPER_FILE.parent.name == "io"  # package data (pyproject io/*.yaml)


@pytest.mark.skipif(not SHARED_PAPER.is_file(), reason="the project's transcription of the paper is not here")
def test_paper_file_agrees_with_the_shared_transcription_number_for_number():
    import yaml

    shared = yaml.safe_load(SHARED_PAPER.read_text())
    ours = load_paper()
    for table in ("table_1_v2t_colour_ssim", "table_2_t2v_colour_ssim"):
        assert ours[table] == shared[table], table
    mine, theirs = ours["table_3_classification_accuracy"], shared["table_3_classification_accuracy"]
    assert mine["columns"] == theirs["columns"] and mine["rows"] == theirs["rows"]


def test_page_helper_autoescapes_html_and_markdown_shows_tags_as_text():
    table = {"caption": "a | b", "columns": ["class", "x"], "rows": [["<b>", 0.12345], ["felt", None]]}
    chance = {"modality": "<m>", "at_chance": ["real"], "classes": 2, "tables": [], "status": "ok", "notes": []}
    context = {"title": "t", "synthetic": False} | _minimal_context(table) | {"classify": [chance]}
    page, summary = render_page("report", context)
    assert "<td>&lt;b&gt;</td><td>0.123</td>" in page and "<td>—</td>" in page
    assert "warning: the &lt;m&gt; classifier ends at chance level" in page and "<m>" not in page
    # Markdown renders raw HTML, so names reach summary.md with < and > as entities (issue 25)
    assert "| class | x |" in summary and "| &lt;b&gt; | 0.123 |" in summary and "<b>" not in summary
    assert '<li class="warning">WARNING: &lt;v&gt;</li>' in page and "- **WARNING: &lt;v&gt;**" in summary


def _minimal_context(table: dict) -> dict:
    run = {"code_version": "c", "built": "b", "python": "3", "torch": "2", "cpus": 1, "preset": "fast", "recipe": "none", "recipe_reason": "as set", "scope": ["all"]}
    return {"dataset": {"source": "s", "path": "p"}, "ingest": {}, "pairs": {}, "run": run, "params_yaml": "",
            "directions": ["v2t"], "figures": {"losses": False, "scores": False, "grid_v2t": False,
                                               "classification": False},
            "verdicts": [{"status": "warning", "line": "WARNING: <v>"}], "not_scored": {}, "pair_kinds": {},
            "duplicates": {}, "modalities": [], "test_per_class": {},
            "quarantine": None, "models": table, "capacity": None, "ms_ssim_note": None, "ssim": [], "classify": [], "timings": None}


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
    assert flat(metrics["v2t"]) == pytest.approx(flat({
        "set_colour_ssim": 0.6, "aligned_colour_ssim": 0.7, "nearest_real_colour_ssim": 0.8, "test_images": 6,
        "real_vs_real": 0.3, "nearest_neighbour": 0.4, "nearest_neighbour_aligned": 0.5, "mean_image": 0.45,
        "mean_image_aligned": 0.55, "flat_mean_colour": 0.5, "flat_mean_colour_aligned": 0.6,
        # distribution metrics, classifier view: best baseline = nearest neighbour (0.2); two-sample: closest to 0.5
        "kid_classifier": {"generated": 0.05, "real_heldout": 0.01, "best_baseline": 0.2},
        "fid_classifier": {"generated": 5.0, "real_heldout": 1.0, "best_baseline": 20.0},
        "two_sample_classifier": {"generated": 0.55, "real_heldout": 0.51, "best_baseline": 0.7},
        "spectrum_pixels": {"generated": 0.005, "real_heldout": 0.001, "best_baseline": 0.02},
        "memorisation_classifier": {"generated": 0.1, "real_heldout": 0.1}}))
    # final epoch (2), mean over seeds 0 and 1: 0.5 + 0.2 + 0.01
    assert flat(metrics["classify"]["tactile"]) == pytest.approx(
        {"real": 0.71, "real+generated": 0.81, "gan_test": 0.5, "gan_test_vs_real": 0.5 / 0.71, "seeds": 2,
         # the classify stage's Wilson interval on the GAN-test's images, so that dvc exp show tells a change from noise
         "gan_test_interval.low": 0.15, "gan_test_interval.high": 0.85, "gan_test_interval.images": 4,
         # real touches of the class the visual classifier reads from each test photo: (2 x 0.5 + 0.5 + 1) / 4
         "gan_test_realistic": 0.625,
         "real_test_images": 4,
         "gain_from_generated.real+generated": 0.1,
         # with its paired interval, so that dvc exp show tells a gain from noise
         "gain_from_generated_paired95.real+generated.low": -0.05,
         "gain_from_generated_paired95.real+generated.high": 0.25,
         # the policy's choice beside real only, so that dvc exp show reads both
         "policy.accuracy": 0.81, "policy.real_only": 0.71, "policy.gain": 0.1, "policy.uses_generated": 1,
         "policy.gain_low": -0.05, "policy.gain_high": 0.25})
    assert metrics["classify"]["visual"]["policy"] == {"accuracy": 0.71, "real_only": 0.71, "gain": 0.0,
                                                       "gain_low": 0.0, "gain_high": 0.0, "uses_generated": 0}
    assert metrics["counts"] == {"classes": 2, "images_kept": 12, "quarantined": 1, "models": 2}


@pytest.mark.slow
def test_report_opens_with_verdicts_and_warns_where_generated_data_fails(tmp_path, capsys):
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in"), out)
    printed = capsys.readouterr().out
    page, summary = (out / "index.html").read_text(), (out / "summary.md").read_text()
    warning = ("WARNING: T2V memorisation (classifier): 0.500 of generated test images are closer to a training "
               "image than any held-out real image is")
    assert f"- **{warning}" in summary and f'<li class="warning">{warning}' in page and f"  {warning}" in printed
    verdicts = summary.index("## Verdicts")
    assert verdicts < summary.index("## Data provenance") < summary.index("Table I:")
    assert summary.index("- V2T KID (classifier): generated 0.05 beats every trivial baseline") > verdicts
    assert ("- tactile classification, real+generated against real: accuracy +0.100, within noise (the paired 95% "
            "interval includes 0) (n = 4 test images)") in summary
    assert "WARNING: V2T" not in summary  # only status warning is marked
    # the data facts: pair kinds per direction and split, the dropped pairs, per-class test n
    assert "- T2V pairs: train 8 (pixel 4, class 4), test 2 (pixel 1, class 1)" in summary
    assert "- WARNING (pairs): v2t: class denim: 2 name pairs promised by the layout were dropped" in summary
    assert "- real tactile test images per class: &lt;b&gt; 2, denim 2" in summary
    assert "pairs are by class only" not in summary
    # distribution and memorisation tables with n, intervals and a reading that does not rank overlaps
    assert "| generated | 6 | 6 | 0.0500 [0.0450, 0.0550] | 5.00 | 0.550 [0.545, 0.555] |" in summary
    assert "| classifier | 0.100 [0.047, 0.201] | 60 | 0.100 [0.047, 0.201] | 60 | 80 | within noise of real held-out" in summary
    assert "<details><summary>V2T: per class</summary>" in page
    # the paper's numbers, row for row, with the protocol caveat
    assert "| ROI without noise | 0.91188 | — | — | not run by the main job (studies: roi_noise) |" in summary
    assert "| 10 |  |  |  | 0.9131 | 0.9058 |" in summary  # Table III tactile, the paper's 10th iteration
    assert "does not state how generated and real images were matched" in page


def test_first_screen_answers_whether_generated_data_helps_before_the_long_lines(tmp_path):
    """Before the verdict lines: per modality the policy chosen on validation with its test accuracy beside real
    only's (intervals, the gain and why), then the verdicts as one direction x family grid coloured by status."""
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in"), out)
    page, summary = (out / "index.html").read_text(), (out / "summary.md").read_text()
    first, verdicts = summary.index("## Does generated data help here?"), summary.index("## Verdicts")
    assert first < verdicts and page.index("Does generated data help here?") < page.index("<h2>Verdicts</h2>")
    assert ("| tactile | chosen on validation; within noise on test (unresolved) | real+generated | 0.810 [0.400, 0.970] "
            "| 0.710 [0.300, 0.950] | +0.100 [-0.050, +0.250] | 4 |") in summary
    assert "| visual | not tested: real only (not scored) | real | 0.710 [0.300, 0.950] | 0.710 [0.300, 0.950] |" in summary
    # more real data: low-data real -> real only, within noise here (the paired interval includes 0), explained below
    assert "| 4 | 0.450 → 0.710 [-0.020, +0.540]: within noise |" in summary
    assert "<td>0.450 → 0.710 [-0.020, +0.540]: within noise</td>" in page
    assert "little room to help the low-data setting" in summary[first:verdicts]
    assert "too few groups" in summary[first:verdicts] and "&lt;b&gt;" in page[:page.index("<h2>Verdicts</h2>")]
    # the grid: one row per family, one column per direction, each cell coloured by its status
    # and a last row: the GAN-test (0.5 [0.15, 0.85]) against the realistic one (0.625): below, within the noise
    assert "| metric family | V2T | T2V |" in summary
    assert "| KID (classifier) | ok (0.05) | ok (0.05) |" in summary
    assert "| memorisation (classifier) | — | warning (0.5) |" in summary
    assert "| GAN-test (of the realistic) | unresolved (0.5 of 0.625) | unresolved (0.5 of 0.625) |" in summary
    grid = page[page.index("Verdicts: metric family x direction"):page.index("<h2>Verdicts</h2>")]
    assert '<tr><td>memorisation (classifier)</td><td class="not-scored">—</td><td class="warning">warning (0.5)</td></tr>' in grid
    assert '<td class="ok">ok (0.05)</td>' in grid and '<td class="unresolved">unresolved (0.5 of 0.625)</td>' in grid
    assert "The last row sets the GAN-test" in summary and "The last row sets the GAN-test" in page
    assert '<td class="not-scored">—</td>' in grid and "td.warning{background:#f8d7da" in page
    assert "Next step" not in summary + page  # trained on pixel pairs, GAN-test within the noise: no recipe advice


@pytest.mark.slow
def test_overlapping_score_intervals_are_flagged_and_greyscale_data_says_ssim(tmp_path):
    out = tmp_path / "reports"
    report(fake_run(tmp_path / "in", greyscale=True, half_width=0.08), out)
    summary = (out / "summary.md").read_text()
    assert "set-to-set SSIM per class" in summary and "Colour-SSIM per class" not in summary
    assert "| (all) | 6 | 0.600 [0.520, 0.680] | 0.800 [0.720, 0.880] | within noise of flat mean colour (intervals overlap) |" in summary
    assert "SSIM (Wang et al. 2004) of the greyscale images" in summary


@pytest.mark.slow
def test_a_one_modality_dataset_gets_a_report_that_says_why_nothing_was_translated(tmp_path, capsys):
    out = tmp_path / "reports"
    metrics = report(fake_one_modality(tmp_path / "in"), out)
    printed = capsys.readouterr().out
    summary, page = (out / "summary.md").read_text(), (out / "index.html").read_text()
    line = "V2T: not scored: translation needs both modalities: this dataset has tactile images only"
    assert f"- {line}" in summary and f"  {line}" in printed and line in page
    assert "- visual classification: not applicable: classification needs at least 2 classes" in summary
    assert "- modalities present: tactile" in summary and "- duplicates found by ingest: exact duplicate files 1, near duplicate files 3" in summary
    assert "- V2T pairs: none" in summary
    assert "Table I:" not in summary and "Table III (tactile)" in summary  # real-only tactile classification
    assert "| (all) | 4 | 0.710 [0.410, 0.910] |" in summary
    assert set(metrics) == {"classify", "counts"} and metrics["counts"]["models"] == 0
    assert metrics["classify"] == {"tactile": pytest.approx({"real": 0.71, "seeds": 2, "real_test_images": 4})}
    assert {p.name for p in (out / "figures").glob("*.png")} == {"classification.png"}


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
    for heading in ("Verdicts", "Data provenance", "Table I:", "Table II:", "Table III (visual)", "Table III (tactile)",
                    "Paper Table I (V2T)", "Paper Table II (T2V)", "V2T: distribution metrics", "T2V: memorisation check",
                    "Stage timings", "SYNTHETIC", "studies/index.html", "MS-SSIM not computed", "Quarantined inputs (1"):
        assert heading in summary and heading in page, heading
    assert "chance level" not in page  # classify gave no at_chance mark: no warning
    figures = {p.name for p in (out / "figures").glob("*.png")}
    assert figures == {"losses.png", "scores.png", "grid_v2t.png", "grid_t2v.png", "nearest_v2t.png",
                       "classification.png", "timings.png"}  # no T2V pairs: no nearest_t2v
    assert page.count("<img ") == 7 and not list(out.glob(".*tmp*"))
    assert '<img src="figures/nearest_v2t.png"' in page and "figures/nearest_v2t.png" in summary


def test_only_a_final_epoch_at_chance_counts_as_ending_at_chance():
    from vtgen.stages.report import at_chance

    rows = [("real", 0, 1, True), ("real", 0, 2, False), ("real", 1, 1, False), ("real", 1, 2, False),
            ("low-data real", 0, 1, False), ("low-data real", 0, 2, True)]
    accuracy = pd.DataFrame(rows, columns=["setting", "seed", "epoch", "at_chance"])
    # 'real' was at chance after its first epoch only (the vt60 tactile case): no warning; 'low-data real' ends there
    assert at_chance({}, accuracy) == ["low-data real"]
    assert at_chance({"settings": {"real": {"at_chance": True}}}, accuracy) == ["real", "low-data real"]


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
    # a training's own times are in its timing.json, not train.json; the models table reads them from there
    runs = model_runs(tmp_path / "in" / "models")
    assert [(r["wall_seconds"], r["seconds_per_iteration"]) for r in runs] == [(3.5, 0.875), (4.5, 1.125)]
    assert not {"stage", "seconds", "finished"} & set(runs[0])  # the command's own fields stay in the timings table
    assert models_table(runs)["wall s"].tolist() == [3.5, 4.5]
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
    _by_class(aligned=True, classes=CLASSES).to_parquet(folders["scores"] / "by_class.parquet")
    strip = folders["scores"] / "nearest_training_v2t.png"
    write_image(strip, np.zeros((16, 24, 3), np.uint8))  # three columns where the table lists two pairs
    with pytest.raises(ValueError, match="nearest_training_v2t.png is 24 x 16 px, not 2 rows of 2 square images"):
        report(folders, tmp_path / "out")
    strip.unlink()
    with pytest.raises(ValueError, match="nearest_training_v2t.png is missing"):
        report(folders, tmp_path / "out")
    _nearest_training(folders["scores"])
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
    assert "about &lt;i&gt;default&lt;/i&gt;. Overrides:" in summary and "<i>" not in summary  # shown, not run
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
    assert figures == {"losses.png", "scores.png", "grid_v2t.png", "grid_t2v.png", "nearest_v2t.png", "nearest_t2v.png",
                       "classification.png", "timings.png"}
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
        # a wide table scrolls in its own box: the page itself never scrolls sideways
        page_width = page.evaluate("() => document.documentElement.scrollWidth")
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        browser.close()
    assert len(images) == 8
    for src, complete, width, height in images:
        assert complete and width > 0 and height > 0, src
    assert all(url.startswith("file://") for url in requests), [u for u in requests if not u.startswith("file://")]
    assert not errors, errors
    for prefix in ("Table I:", "Table II:", "Table III (visual)", "Table III (tactile)", "Trained generators"):
        assert any(c.startswith(prefix) for c in captions), prefix
    assert min(rows) >= 2  # a header and at least one row each
    assert page_width <= 1200, page_width
    assert SCREENSHOT.stat().st_size > 10_000


def test_more_real_data_says_whether_all_real_images_beat_the_low_data_share_beyond_the_paired_interval():
    from vtgen.io.report_verdicts import more_real_data

    settings = {"low-data real": {"final_mean": 0.225}, "real": {"final_mean": 0.239}}
    def gain(low, high):
        return {"paired_interval": [low, high], "within_noise": low <= 0 <= high}
    assert more_real_data({"settings": settings, "more_real_data": gain(-0.05, 0.08)}) \
        == "0.225 → 0.239 [-0.050, +0.080]: within noise"
    assert more_real_data({"settings": settings, "more_real_data": gain(0.01, 0.03)}) \
        == "0.225 → 0.239 [+0.010, +0.030]: more real data helps"
    assert more_real_data({"settings": settings, "more_real_data": gain(-0.3, -0.1)}).endswith(": more real data hurts")
    assert more_real_data({"settings": settings}) == "0.225 → 0.239"  # no paired gain: no verdict
    assert more_real_data({"settings": {"real": {"final_mean": 0.4}}}) == "—"


def test_gan_test_caveat_says_what_the_generator_was_told():
    """Told each image's class, the caveat warns that GAN-test rewards following the class; told what a reader of
    the input read (`inferred`), it names the reader and says the reading bounds the GAN-test; told nothing, none."""
    from vtgen.stages.report import conditioned_gan_test_note

    summary = {"gan_test": {"final_mean": 0.197}, "settings": {"real": {"final_mean": 0.239}}}
    told = conditioned_gan_test_note("tactile", summary, [{"direction": "v2t", "conditioning": "class"}])
    assert "told each image's class (conditioning class)" in told and "0.197" in told and "0.239" in told
    inferred = conditioned_gan_test_note("tactile", summary, [{"direction": "v2t", "conditioning": "inferred",
                                                               "input_reader": "features"}])
    assert "input reader (features)" in inferred and "never the image's own class" in inferred
    older = conditioned_gan_test_note("tactile", summary, [{"direction": "v2t", "conditioning": "inferred"}])
    assert "input reader (network)" in older  # train.json from before the reader was recorded
    assert conditioned_gan_test_note("tactile", summary, [{"direction": "v2t", "conditioning": "none"},
                                                          {"direction": "t2v", "conditioning": "class"}]) is None



def test_gan_test_caveat_gives_the_figure_told_the_class_read_from_the_input():
    """Told the class, and scored again told the class a reader read from each input (the classify stage's
    gan_test_read, the generate stage's counts summed over scopes): the caveat gives that GAN-test with its
    interval and how often the reader read the input's own class, as goal 3's figure; metrics.json carries it."""
    from vtgen.io.report_metrics import classify_headline
    from vtgen.stages.report import conditioned_gan_test_note, read_class_counts

    summary = {"gan_test": {"final_mean": 0.479}, "settings": {"real": {"final_mean": 0.263}},
               "gan_test_read": {"final_mean": 0.254, "interval": [0.203, 0.313], "images": 240}}
    generate = {"scopes": {"all": {"test": 120, "told_the_class_read": {"reader": "features", "inputs": 120,
                                                                         "read_correctly": 40}},
                           "felt": {"test": 60, "told_the_class_read": {"reader": "features", "inputs": 60,
                                                                          "read_correctly": 20}},
                           "wool": {"status": "not applicable: one class"}}}
    read = read_class_counts(generate)
    assert read == {"reader": "features", "inputs": 180, "read_correctly": 60}
    assert read_class_counts({"scopes": {"all": {"test": 120}}}) is None
    note = conditioned_gan_test_note("visual", summary, [{"direction": "t2v", "conditioning": "class"}], read)
    assert "0.479" in note and "0.254 [0.203, 0.313]" in note and "240 test translations" in note
    assert "hand-crafted-feature reader reads from each input (its own class for 60 of 180)" in note and "goal 3" in note
    plain = conditioned_gan_test_note("visual", {k: v for k, v in summary.items() if k != "gan_test_read"},
                                      [{"direction": "t2v", "conditioning": "class"}], read)
    assert "0.254" not in plain and "goal 3" not in plain
    accuracy = pd.DataFrame({"setting": ["real"], "seed": [0], "epoch": [1], "test_accuracy": [0.263],
                             "gan_test_accuracy": [0.479]})
    assert classify_headline({"accuracy": accuracy, "summary": summary})["gan_test_read"] == 0.254
    assert "gan_test_read" not in classify_headline({"accuracy": accuracy, "summary": {}})


def test_realistic_gan_test_reads_both_confusions_and_what_the_generator_was_told():
    """The target modality's judge (tactile: class 0 called right at 0.5, class 1 at 1.0) scores real images of
    the class each input shows: read by the input modality's classifier unless the generator was told it."""
    from vtgen.io.report_metrics import realistic_gan_tests
    from vtgen.stages.report import realistic_gan_test_note

    def entry(confusion, classes=("a", "b")):
        return {"summary": {"classes": list(classes), "real_confusion": confusion}}

    classify = {"visual": entry([[2, 0], [1, 1]]), "tactile": entry([[1, 1], [0, 2]])}
    runs = [{"direction": "v2t", "conditioning": "none"}, {"direction": "t2v", "conditioning": "class"}]
    found = realistic_gan_tests(classify, runs)
    # V2T told nothing: photos read (0,0), (0,0), (1,0), (1,1) -> touches of class 0, 0, 0, 1: 0.5 + 0.5 + 0.5 + 1
    assert found["tactile"] == {"value": 0.625, "told_class": False, "inputs": 4}
    # T2V told the class: each touch becomes a photo of its own class, called right at 1.0 and 0.5
    assert found["visual"] == {"value": 0.75, "told_class": True, "inputs": 4}
    untold = realistic_gan_tests(classify, [{"direction": "t2v", "conditioning": "inferred"}])
    assert untold["visual"]["value"] == pytest.approx((1 * 1.0 + 1 * 0.5 + 2 * 0.5) / 4)  # the touches as read
    # classes that differ between the two stages, or a confusion missing: no number rather than a wrong one
    assert realistic_gan_tests({"visual": entry([[2, 0], [1, 1]], ("a", "c")), "tactile": classify["tactile"]}, runs) == {}
    assert realistic_gan_tests({"visual": {"summary": {"classes": ["a", "b"]}}, "tactile": classify["tactile"]}, runs) == {}
    note = realistic_gan_test_note("tactile", {"gan_test": {"final_mean": 0.061}}, found["tactile"])
    assert "realistic GAN-test 0.625 beside the GAN-test's 0.061" in note and "visual real-only classifier" in note
    assert "n = 4 test inputs" in note
    assert realistic_gan_test_note("tactile", {"gan_test": {}}, found["tactile"]) is None


def test_the_gan_test_column_is_ok_at_the_realistic_level_and_a_warning_below_it_beyond_the_noise():
    from vtgen.io.report_verdicts import gan_test_verdicts

    def data(gan, realistic):
        return {"classify": {"tactile": {"summary": {"gan_test": gan}}},
                "realistic_gan_test": {"tactile": {"value": realistic}}}

    def status(gan, realistic):
        return [v["status"] for v in gan_test_verdicts(data(gan, realistic))]

    assert status({"final_mean": 0.30, "interval": [0.22, 0.39]}, 0.25) == ["ok"]
    assert status({"final_mean": 0.20, "interval": [0.13, 0.28]}, 0.25) == ["unresolved"]
    assert status({"final_mean": 0.06, "interval": [0.03, 0.12]}, 0.16) == ["warning"]  # the vt60 default's V2T
    assert status({"final_mean": 0.12, "interval": [0.07, 0.19], "at_chance": True}, 0.11) == ["warning"]
    (verdict,) = gan_test_verdicts(data({"final_mean": 0.06, "interval": [0.03, 0.12]}, 0.162))
    assert verdict["direction"] == "v2t" and verdict["cell"] == "warning (0.06 of 0.162)"
    assert gan_test_verdicts(data({}, 0.2)) == [] and gan_test_verdicts(data({"final_mean": 0.1, "interval": [0, 0.2]}, None)) == []


def test_the_grid_has_the_gan_test_column_and_says_so_only_where_there_is_a_realistic_gan_test():
    from vtgen.io.report_verdicts import GAN_TEST_FAMILY, verdict_grid

    scored = {"score_summary": {"verdicts": [{"direction": "v2t", "family": "KID (classifier)", "status": "ok",
                                              "generated": 0.05}]}}
    plain_grid = verdict_grid(scored)
    assert plain_grid["families"] == ["KID (classifier)"] and not plain_grid["gan_test_column"]
    with_oracle = verdict_grid(scored | {"classify": {"tactile": {"summary": {"gan_test": {
        "final_mean": 0.06, "interval": [0.03, 0.12]}}}}, "realistic_gan_test": {"tactile": {"value": 0.16}}})
    assert with_oracle["families"][-1] == GAN_TEST_FAMILY and with_oracle["gan_test_column"]
    assert with_oracle["rows"][0]["cells"][-1] == {"status": "warning", "text": "warning (0.06 of 0.16)"}


def test_the_report_points_to_the_long_recipe_only_where_class_pairs_fall_short_without_it():
    """recipe_advice names the directions whose GAN-test is below the realistic one beyond the noise, when their
    model trained the class-pair objective by default or with the quick recipe (train.json); the text macro words the next-step line
    the page shows."""
    from vtgen.io.report_pages import environment
    from vtgen.io.report_verdicts import recipe_advice

    def data(recipe="none", objective="class_gan", gan=(0.06, [0.03, 0.12])):
        return {"models": [{"direction": "v2t", "recipe": recipe, "objective": {"name": objective}}],
                "classify": {"tactile": {"summary": {"gan_test": {"final_mean": gan[0], "interval": gan[1]}}}},
                "realistic_gan_test": {"tactile": {"value": 0.162}}}

    assert recipe_advice(data()) == ["V2T"]  # the vt60 quick recipe's V2T: 0.06 [0.03, 0.12] of 0.162
    assert recipe_advice(data(recipe="quick")) == ["V2T"]  # the short recipe: the longer one is the next step
    assert recipe_advice(data(recipe="fabric")) == []  # the long recipe was used: nothing to point to
    assert recipe_advice(data(objective="pix2pix")) == []  # aligned pairs train pix2pix
    assert recipe_advice(data(gan=(0.15, [0.09, 0.23]))) == []  # within the noise of the realistic level
    chosen = dict(data(), run={"recipe_reason": "auto: class pairs only, but the training photos are scenes"})
    assert recipe_advice(chosen) == []  # recipe auto kept none for object photos: the fabric recipe is not for them
    assert recipe_advice(dict(data(), run={"recipe_reason": "as set"})) == ["V2T"]
    both = data()
    both["models"].append(dict(both["models"][0], direction="t2v"))
    both["classify"]["visual"] = both["classify"]["tactile"]
    both["realistic_gan_test"]["visual"] = {"value": 0.9}
    assert recipe_advice(both) == ["V2T", "T2V"]  # the grid's order, not the modalities'
    line = environment().get_template("report_text.txt").module.recipe_advice(["V2T", "T2V"])
    assert line.startswith("Next step: V2T and T2V fall short") and "dvc exp run -S translation.recipe=fabric" in line


def test_metrics_carry_the_image_checks_of_the_score_stage():
    """metrics.json's ``brightness_outside`` and ``fixed_pattern_share`` per direction are the score stage's
    brightness-range and fixed-pattern verdicts (so `dvc exp show` compares them); a direction without a verdict gets no key for it."""
    from vtgen.io.report_metrics import checks_headline

    summary = {"verdicts": [
        {"direction": "v2t", "metric": "memorisation", "generated": 0.5, "real_heldout": 0.0},
        {"direction": "v2t", "metric": "brightness", "generated": 0.491667, "real_heldout": 0.125},
        {"direction": "v2t", "metric": "fixed_pattern", "generated": 0.2, "real_heldout": 0.01, "dots": 15},
        {"direction": "t2v", "metric": "kid", "generated": 1.0}]}
    assert checks_headline(summary, "v2t") == {"brightness_outside": {"generated": 0.491667, "real_heldout": 0.125},
                                               "fixed_pattern_share": {"generated": 0.2, "real_heldout": 0.01}}
    assert checks_headline(summary, "t2v") == {}
    assert checks_headline({}, "v2t") == {}
