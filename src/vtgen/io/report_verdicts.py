"""What the report opens with: the verdict lines, the direction x family verdict grid and the policy rows.

The verdicts themselves are the score and classify stages' (their summary.json); this module words
them, adds a line for every direction not scored (and why), and marks warnings.
"""

from __future__ import annotations

from vtgen.core.domain import DIRECTIONS, MODALITIES, direction_producing
from vtgen.io.report_pages import interval_cell


def translation_reason(summary: dict, direction: str) -> str | None:
    """The reason a stage summary (pairs or ingest) records in its ``translation`` entry, overall or per
    direction, for ``direction`` having no translation, or None when it records none."""
    entry = summary.get("translation")
    if isinstance(entry, dict) and isinstance(entry.get(direction), (dict, str)):
        entry = entry[direction]
    if isinstance(entry, dict):
        return entry.get("reason") or None
    return entry or None if isinstance(entry, str) else None


def not_scored(data: dict) -> dict[str, str]:
    """{direction: why it has no scores} for the directions without scores (a one-modality dataset:
    the pairs stage's reason first, then the ingest stage's, the train stage's status, the score stage's)."""
    recorded = data["score_summary"].get("not_scored") or {}
    scored = set(data["by_class"]["direction"])
    result = {}
    for direction in DIRECTIONS:
        if direction in scored and direction not in recorded:
            continue
        statuses = [str(r["status"]).removeprefix("not applicable: ") for r in data["models"]
                    if r["direction"] == direction and str(r.get("status", "ok")).startswith("not applicable")]
        result[direction] = (translation_reason(data["pairs"], direction) or translation_reason(data["ingest"], direction)
                             or (statuses[0] if statuses else None)
                             or recorded.get(direction) or "the score stage has no scores for this direction")
    return result


VERDICT_MARKS = {"warning": "WARNING: ", "unresolved": "", "ok": "", "not scored": ""}


def verdict_lines(data: dict) -> list[dict]:
    """The lines the report opens with: ``{"status", "line"}`` per direction and metric family (the
    score stage's verdicts), per classification comparison, and per direction or modality not scored."""
    found, skipped, lines = data["score_summary"].get("verdicts") or [], not_scored(data), []

    def add(status: str, text: str) -> None:
        lines.append({"status": status, "line": VERDICT_MARKS.get(status, "") + text})

    for direction in DIRECTIONS:
        if direction in skipped:
            add("not scored", f"{direction.upper()}: not scored: {skipped[direction]}")
            continue
        mine = [v for v in found if v.get("direction") == direction]
        if not mine:
            add("unresolved", f"{direction.upper()}: no verdict (the score stage's summary.json has none for it)")
        for verdict in mine:
            add(verdict.get("status", "ok"), verdict["text"])
    for modality, entry in data["classify"].items():
        summary = entry["summary"]
        if summary.get("status", "ok") != "ok":
            add("not scored", f"{modality} classification: {summary['status']}")
            continue
        n = (summary.get("counts") or {}).get("real_test", "?")
        for item in summary.get("comparisons") or []:
            add("unresolved" if item["within_noise"] else "ok",
                f"{modality} classification, {item['setting']} against {item['against']}: accuracy "
                f"{item['difference']:+.3f}, {item['verdict']} (n = {n} test images)")
        for setting in entry["at_chance"]:
            add("warning", f"{modality} classification: '{setting}' ends at chance level; its accuracies say nothing "
                           f"about the generated data")
    return lines


# ---------------------------------------------------------------- the first screen


VERDICT_COLOURS = ("ok", "unresolved", "warning", "uninformative", "not scored")


def more_real_data(summary: dict) -> str:
    """The test accuracy of real only with the low-data share of the training images and with all of them
    (``low → all``) and whether all is better beyond the paired 95% interval of their difference (summary.json's
    ``more_real_data``); an em dash when either accuracy is missing. Within noise, more real images did not help the
    classifier, so generated images learned from those same images have little room to help the low-data setting."""
    settings = summary.get("settings") or {}
    low, full = settings.get("low-data real") or {}, settings.get("real") or {}
    if low.get("final_mean") is None or full.get("final_mean") is None:
        return "—"
    text = f"{low['final_mean']:.3f} → {full['final_mean']:.3f}"
    gain = summary.get("more_real_data")
    if not gain:
        return text
    low_gain, high_gain = gain["paired_interval"]
    return text + (f" [{low_gain:+.3f}, {high_gain:+.3f}]: "
                   + ("within noise" if gain["within_noise"] else "more real data helps" if low_gain > 0
                      else "more real data hurts"))


def policy_rows(data: dict) -> list[dict]:
    """"Does generated data help here?": per modality, the classify stage's policy (the setting chosen on the
    validation split, or real only and why) and its test accuracy beside real only's, with intervals, and
    :func:`more_real_data`."""
    rows = []
    for modality, entry in data["classify"].items():
        summary = entry["summary"]
        policy = summary.get("policy")
        if summary.get("status", "ok") != "ok" or not policy:
            rows.append({"modality": modality, "answer": "not measured", "status": "not scored",
                         "chosen": "—", "accuracy": "—", "real": "—", "gain": "—", "n": "—", "more_real": "—",
                         "why": summary.get("status") if summary.get("status", "ok") != "ok"
                         else "this classify run predates the policy (no summary.json policy)"})
            continue
        test = policy["test"]
        gain = test.get("gain")
        low, high = test.get("gain_interval") or (None, None)
        if not policy["uses_generated"]:
            answer, status = (("no: real only", "unresolved") if policy.get("candidates")
                              else ("not tested: real only", "not scored"))
        else:
            answer = "yes" if low is not None and low > 0 else "chosen on validation; within noise on test"
            status = "ok" if low is not None and low > 0 else "unresolved"
        if gain is not None and high is not None and high < 0:
            status = "warning"  # below real only beyond the interval: the guarantee failed here
        rows.append({"modality": modality, "answer": answer, "status": status, "chosen": policy["chosen"],
                     "accuracy": interval_cell(test.get("accuracy"), *(test.get("interval") or (None, None))),
                     "real": interval_cell(test.get("real_accuracy"), *(test.get("real_interval") or (None, None))),
                     "gain": "—" if gain is None else f"{gain:+.3f}" + (f" [{low:+.3f}, {high:+.3f}]"
                                                                         if low is not None else ""),
                     "n": test.get("images", "—"), "more_real": more_real_data(summary),
                     "why": policy.get("reason", "")})
    return rows


GAN_TEST_FAMILY = "GAN-test (of the realistic)"


def gan_test_verdicts(data: dict) -> list[dict]:
    """One verdict per direction whose target modality has a GAN-test and a realistic GAN-test (the report's
    ``realistic_gan_test``): ok when the GAN-test reaches the realistic one, unresolved when below it but
    within the GAN-test's 95% Wilson interval, warning when below beyond that interval or at chance; ``cell`` is
    the grid's text."""
    found = []
    for modality in MODALITIES:
        gan = (((data.get("classify") or {}).get(modality) or {}).get("summary") or {}).get("gan_test") or {}
        realistic = ((data.get("realistic_gan_test") or {}).get(modality) or {}).get("value")
        value, interval = gan.get("final_mean"), gan.get("interval")
        if value is None or realistic is None or not interval:
            continue
        status = ("warning" if gan.get("at_chance") or interval[1] < realistic
                  else "ok" if value >= realistic else "unresolved")
        found.append({"direction": direction_producing(modality), "family": GAN_TEST_FAMILY, "status": status,
                      "cell": f"{status} ({value:.3g} of {realistic:.3g})"})
    return found


def recipe_advice(data: dict) -> list[str]:
    """The directions (upper case, the grid's order) whose GAN-test falls below the realistic one beyond the
    noise (:func:`gan_test_verdicts`: warning) where a model trained the class-pair objective with the default
    settings or the quick recipe (train.json's ``objective`` class_gan, ``recipe`` none or quick): there the report
    points to params.yaml's longer fabric recipe. Empty otherwise, and where ``translation.recipe: auto`` chose
    none from the data (``data["run"]["recipe_reason"]``: photos of scenes, for which the fabric recipe was not made)."""
    if (data.get("run") or {}).get("recipe_reason", "as set") != "as set":
        return []
    plain = {run["direction"] for run in data.get("models") or []
             if (run.get("objective") or {}).get("name") == "class_gan" and run.get("recipe", "none") in ("none", "quick")}
    short = {v["direction"] for v in gan_test_verdicts(data) if v["status"] == "warning"}
    return [d.upper() for d in DIRECTIONS if d in short & plain]


def verdict_grid(data: dict) -> dict | None:
    """The score stage's verdicts as one direction x family grid: ``{"families", "rows": [{"direction",
    "cells": [{"status", "text"}]}], "gan_test_column"}``, each cell the status (VERDICT_COLOURS) and a short value, and a last
    family for the GAN-test against the realistic one (:func:`gan_test_verdicts`); None when the score stage
    has no verdicts. The report shows it with a row per family and a column per direction (the families outnumber
    the directions, so it fits the page)."""
    scored = data["score_summary"].get("verdicts") or []
    if not scored:
        return None
    found = scored + gan_test_verdicts(data)
    families = list(dict.fromkeys(v["family"] for v in found if v.get("family")))
    rows = []
    for direction in sorted({v["direction"] for v in found}, key=lambda d: list(DIRECTIONS).index(d)
                            if d in DIRECTIONS else 9):
        mine = {v["family"]: v for v in found if v.get("direction") == direction}
        cells = []
        for family in families:
            v = mine.get(family)
            if v is None:
                cells.append({"status": "not scored", "text": "—"})
                continue
            value = v.get("generated")
            text = v.get("cell") or v.get("status", "ok") + ("" if value is None else f" ({value:.3g})")
            cells.append({"status": v.get("status", "ok"), "text": text})
        rows.append({"direction": direction.upper(), "cells": cells})
    return {"families": families, "rows": rows, "gan_test_column": GAN_TEST_FAMILY in families}
