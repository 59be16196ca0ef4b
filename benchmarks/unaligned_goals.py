"""Issue 24's goal numbers (items 1-4) of a finished run, with pass/fail per item: one command, one table.

Reads the score stage's ``data/scores/summary.json`` (its ``goals``: diversity ratios, recall, coverage,
KID, FID and memorisation, each with a 95% interval and n) and, for item 3, the classify numbers of
``reports/metrics.json`` (GAN-test and real-only accuracy per modality). Prints a markdown table.

1. No collapse: within-class diversity ratio (median over classes; 64 px grey pixels and classifier
   features) at least 0.5; recall and coverage (classifier view) of generated at least half of real
   held-out's.
2. Beats the no-learning baselines: KID and FID (classifier view) of generated below flat mean colour's
   and mean image's beyond the intervals (generated's upper bound below the baseline's lower bound; a
   bound missing counts as overlap). Blurred real and nearest neighbour are shown (stretch goal). Each
   row is followed by a "paired" row: generated's value minus the baseline's on the shared reference,
   with the score stage's paired interval (``generated_minus``); it passes when that interval lies below
   0. Two sets' separate intervals both carry the shared reference's noise, so they can overlap where
   the difference is certain; the last line counts the goal both ways. Its target shows the same difference
   with real held-out images in generated's place (``real_heldout_minus``): where even that interval reaches
   0, the row cannot pass at this n whatever the generator draws. Beside them, not counted (the
   issue states item 2 over all classes): the class-wise KID's paired difference (mean over classes of
   each class's KID against that class's real images), which a set drawing one look for several
   classes cannot pass.
3. Recognisable: GAN-test of the generated modality at least 0.8 x the lower of the two real-only
   accuracies. The goal is stated for a generator not told the class: where ``models/<direction>/all/train.json``
   says the model was told it (``class`` or ``reference``), the row shows the figure and counts as n/a, and
   a second row counts the GAN-test of the same model told instead the class a reader reads from each test
   input (metrics.json ``gan_test_read``: the generate stage translates them, the classify stage scores them),
   where the run has it.
4. No copying: memorisation rate of generated not above the upper bound of real held-out's interval.

Shown, not counted (the issue measures item 1 by diversity): whether outputs follow their inputs within a class
(the score stage's Mantel r, in grey 16 x 16 means and in the real-only classifiers' features, with a one-sided
permutation p below 0.05 against within-class shuffles).

    python benchmarks/unaligned_goals.py                 # the run in the working directory
    python benchmarks/unaligned_goals.py /path/to/run    # a run folder (data/scores, reports)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

MODALITY = {"v2t": ("visual", "tactile"), "t2v": ("tactile", "visual")}  # (input, output)


def _fmt(entry: dict | None) -> str:
    if not entry or entry.get("value") is None:
        return "-"
    low, high = entry.get("low"), entry.get("high")
    interval = "" if low is None or high is None else f" [{low:.3g}, {high:.3g}]"
    n = f", n {entry['n']}" if "n" in entry else f", {entry['classes']} classes" if "classes" in entry else ""
    return f"{entry['value']:.3g}{interval}{n}"


def _real_in_place(entry: dict | None, baseline: str) -> str:
    """The same paired difference with real held-out images in generated's place (the score stage's
    ``real_heldout_minus``): how far real images themselves beat the baseline at this n."""
    real = ((entry or {}).get("real_heldout_minus") or {}).get(baseline)
    return f" (real held-out in its place: {_fmt(real)})" if real and real.get("value") is not None else ""


def _verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else "PASS" if ok else "FAIL"


TOLD_THE_CLASS = ("class", "reference")  # conditionings that hand the generator its input's class


def goal_rows(goals: dict, classify: dict, conditioning: dict | None = None) -> list[tuple[str, str, str, str, str]]:
    """(direction, item, measured, target, verdict) rows for issue 24's items 1-4; ``conditioning`` maps a
    direction to its model's conditioning kind (item 3 is n/a for a model told the class)."""
    conditioning = conditioning or {}
    rows = []
    for direction in sorted(goals):
        g = goals[direction]
        for view in ("pixels", "classifier"):
            entry = g.get(f"diversity_{view}")
            ok = None if not entry or entry.get("value") is None else entry["value"] >= 0.5
            rows.append((direction, f"1 diversity ratio ({view})", _fmt(entry), ">= 0.5", _verdict(ok)))
        for metric in ("recall", "coverage"):
            entry = g.get(f"{metric}_classifier") or {}
            gen, real = entry.get("generated"), entry.get("real_heldout")
            ok = None if not gen or not real or gen.get("value") is None or real.get("value") is None \
                else gen["value"] >= 0.5 * real["value"]
            target = "-" if not real or real.get("value") is None else f">= {0.5 * real['value']:.3g} (half of real {_fmt(real)})"
            rows.append((direction, f"1 {metric} (classifier)", _fmt(gen), target, _verdict(ok)))
        for view in ("pixels", "classifier"):
            entry = g.get(f"following_{view}")
            if not entry or entry.get("value") is None:
                continue
            ok = None if entry.get("p") is None else entry["p"] < 0.05  # the score stage's verdict (FOLLOWING_LEVEL)
            rows.append((direction, f"1 outputs follow their inputs within a class ({view}; not counted)",
                         f"r {entry['value']:.3g} (p {entry.get('p', math.nan):.3g}, n {entry.get('n', '?')})",
                         f"p below 0.05 (95% of within-class shuffles: [{entry.get('low', math.nan):.3g}, "
                         f"{entry.get('high', math.nan):.3g}])", _verdict(ok)))
        for metric in ("kid", "fid"):
            entry = g.get(f"{metric}_classifier") or {}
            gen = entry.get("generated")
            for baseline, item in (("flat_mean_colour", "2"), ("mean_image", "2"), ("blurred_real", "2 stretch"),
                                   ("nearest_neighbour", "2 stretch")):
                base = entry.get(baseline)
                ok = None
                if gen and base and gen.get("value") is not None and base.get("value") is not None:
                    ok = (gen.get("high") is not None and base.get("low") is not None
                          and gen["high"] < base["low"])
                rows.append((direction, f"{item} {metric.upper()} vs {baseline}", _fmt(gen),
                             f"below {_fmt(base)}", _verdict(ok)))
                diff = (entry.get("generated_minus") or {}).get(baseline)
                if diff and diff.get("value") is not None:
                    ok = diff.get("high") is not None and diff["high"] < 0
                    rows.append((direction, f"{item} paired {metric.upper()} minus {baseline}", _fmt(diff),
                                 "below 0" + _real_in_place(entry, baseline), _verdict(ok)))
        classwise = (g.get("kid_classwise_classifier") or {}).get("generated_minus") or {}
        for baseline in ("flat_mean_colour", "mean_image"):
            diff = classwise.get(baseline)
            if diff and diff.get("value") is not None:
                ok = diff.get("high") is not None and diff["high"] < 0
                rows.append((direction, f"2 class-wise paired KID minus {baseline} (not counted)", _fmt(diff),
                             "below 0" + _real_in_place(g.get("kid_classwise_classifier"), baseline), _verdict(ok)))
        source, target = MODALITY[direction]
        gan = (classify.get(target) or {}).get("gan_test")
        reals = [(classify.get(m) or {}).get("real") for m in (source, target)]
        ok = None if gan is None or None in reals else gan >= 0.8 * min(reals)
        threshold = "-" if None in reals else f">= {0.8 * min(reals):.3g} (0.8 x min real-only {min(reals):.3g})"
        realistic = (classify.get(target) or {}).get("gan_test_realistic")  # the report's realistic GAN-test
        if realistic is not None:
            threshold += f"; real images in place of the outputs: {realistic:.3g}"
        told = conditioning.get(direction) in TOLD_THE_CLASS
        item = f"3 GAN-test ({target})" + (f", told the class ({conditioning[direction]})" if told else "")
        gan_entry = {"value": gan, **((classify.get(target) or {}).get("gan_test_interval") or {})}
        rows.append((direction, item, _fmt(gan_entry), threshold, _verdict(None if told else ok)))
        read = (classify.get(target) or {}).get("gan_test_read")  # the same model told the class read from its input
        if told and read is not None:
            ok = None if None in reals else read >= 0.8 * min(reals)
            entry = {"value": read, **((classify.get(target) or {}).get("gan_test_read_interval") or {})}
            rows.append((direction, f"3 GAN-test ({target}), told the class read from the input", _fmt(entry),
                         threshold, _verdict(ok)))
        mem = {k: v for k, v in g.items() if k.startswith("memorisation_")}
        for name, entry in mem.items():
            gen, real = entry.get("generated"), entry.get("real_heldout")
            ok = None if not gen or not real or gen.get("value") is None or real.get("high") is None \
                else gen["value"] <= real["high"]
            rows.append((direction, f"4 {name.replace('_', ' (', 1)})", _fmt(gen), f"<= real held-out {_fmt(real)}",
                         _verdict(ok)))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", nargs="?", type=Path, default=Path("."), help="a run folder (default: here)")
    args = parser.parse_args()
    summary_path = args.run / "data/scores/summary.json"
    if not summary_path.is_file():
        sys.exit(f"{summary_path}: not found; run the score stage first")
    goals = json.loads(summary_path.read_text()).get("goals")
    if not goals:
        sys.exit(f"{summary_path}: no 'goals' (written by the score stage since issue 26/24); rerun the score stage")
    metrics_path = args.run / "reports/metrics.json"
    classify = json.loads(metrics_path.read_text()).get("classify", {}) if metrics_path.is_file() else {}
    if not classify:
        print(f"note: {metrics_path} has no classify numbers: item 3 is n/a", file=sys.stderr)
    for modality, entry in classify.items():  # the GAN-tests' intervals and n, from the classify stage's summary
        summary = args.run / "data/classify" / modality / "summary.json"
        found = json.loads(summary.read_text()) if summary.is_file() else {}
        for name in ("gan_test", "gan_test_read"):
            figure = found.get(name) or {}
            if figure.get("interval"):
                entry[f"{name}_interval"] = {"low": figure["interval"][0], "high": figure["interval"][1],
                                             "n": figure["images"]}
    conditioning = {}
    for direction in MODALITY:
        record = args.run / "models" / direction / "all" / "train.json"
        if record.is_file():
            conditioning[direction] = json.loads(record.read_text()).get("conditioning", "none")
    rows = goal_rows(goals, classify, conditioning)
    print("| direction | goal item | generated (95% interval, n) | target | verdict |")
    print("|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    counted = [r[4] for r in rows if not any(word in r[1] for word in ("stretch", "paired", "not counted"))]
    print(f"\n{counted.count('PASS')} pass, {counted.count('FAIL')} fail, {counted.count('n/a')} n/a "
          f"(stretch rows not counted; item 2 by separate intervals)")
    paired = {(r[0], r[1].replace(" paired", "").replace(" minus ", " vs ")): r[4] for r in rows if "paired" in r[1]}
    if paired:
        by_pairs = [paired.get((r[0], r[1]), r[4]) for r in rows
                    if not any(word in r[1] for word in ("stretch", "paired", "not counted"))]
        print(f"{by_pairs.count('PASS')} pass, {by_pairs.count('FAIL')} fail, {by_pairs.count('n/a')} n/a "
              f"with item 2 read from the paired differences")


if __name__ == "__main__":
    main()
