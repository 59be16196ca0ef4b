"""Memory and time requests per rule from the peaks a finished run measured (its timing.json files).

    python workflow/profiles/slurm/measured_requests.py [RUN] [--data X] [--train Y] [--margin M]

RUN is the project folder of a finished run (default: the current folder). Each stage command records its wall
time and peak resident memory in ``timing.json`` in its output folder (``peak_rss_mb``, the stage process;
``peak_rss_children_mb``, its largest worker process; a worker's RSS counts the pages it shares with the stage
process, so the sum below is an upper bound). For every rule this prints the measured peaks and the
``set-resources`` lines for workflow/profiles/slurm/config.yaml:

    mem_mb  = round up to 100 MB of  M x (peak_rss_mb + workers x peak_rss_children_mb) x S  +  JOB_OVERHEAD_MB
    runtime = round up to 5 min of   M x seconds x S  (at least 10 min)

S is the data factor: ``--data`` (your data over the measured run's, in tiles x pixels per tile) for every rule
but train, ``--train`` for train (your training work over the measured run's: iterations x batch x pixels per
tile for time; memory follows the tiles it holds, so give the larger of the two). The data stages hold metadata
rows, training and classification hold their tiles, so memory grows about linearly with the data; scaling the
whole peak (the Python and torch floor too) errs on the safe side. Each request is multiplied by Snakemake's
``attempt``, so a job killed for memory or time is resubmitted once with twice the request.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

JOB_OVERHEAD_MB = 400  # the two Snakemake processes inside every SLURM job: 183-185 MB for the batch script's and
#                        181-200 MB for the job step's (sacct MaxRSS of the step minus the stage's peak_rss_mb), 9 jobs
#                        of the tiny main job on the test cluster (docs/scaling.md)
WORKER_KEYS = {"render": "synthetic.workers", "roi": "ingest.workers"}  # rules whose stage starts worker processes


def measured(run: Path) -> dict[str, dict]:
    """{rule: {"seconds", "peak_rss_mb", "peak_rss_children_mb"}} from every timing.json of ``run``, the largest
    per rule (a rule with several jobs, e.g. train per direction, is sized for its largest job)."""
    rules: dict[str, dict] = {}
    for path in sorted(run.glob("**/timing.json")):
        if ".snakemake" in path.parts or "studies_work" in path.parts:
            continue
        record = json.loads(path.read_text())
        if "peak_rss_mb" not in record:
            continue  # written by a vtgen version that did not measure memory
        rule = record["stage"]
        old = rules.setdefault(rule, {"seconds": 0.0, "peak_rss_mb": 0.0, "peak_rss_children_mb": 0.0})
        for key in old:
            old[key] = max(old[key], float(record.get(key, 0.0)))
    return rules


def workers(params: dict, rule: str) -> int:
    if rule not in WORKER_KEYS:
        return 0
    section, key = WORKER_KEYS[rule].split(".")
    return int(params.get(section, {}).get(key, 1))


def requests(peaks: dict[str, dict], params: dict, data: float = 1.0, train: float = 1.0,
             margin: float = 2.0) -> dict[str, dict]:
    """{rule: {"mem_mb", "runtime"}} by the formula of this module's docstring."""
    out = {}
    for rule, peak in sorted(peaks.items()):
        scale = train if rule == "train" else data
        memory = peak["peak_rss_mb"] + workers(params, rule) * peak["peak_rss_children_mb"]
        out[rule] = {"mem_mb": int(math.ceil((margin * memory * scale + JOB_OVERHEAD_MB) / 100) * 100),
                     "runtime": max(10, int(math.ceil(margin * peak["seconds"] * scale / 60 / 5) * 5))}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", nargs="?", default=".", help="folder of a finished run (default: .)")
    parser.add_argument("--data", type=float, default=1.0, help="your data over the measured run's (default 1)")
    parser.add_argument("--train", type=float, default=1.0, help="your training work over the measured run's")
    parser.add_argument("--margin", type=float, default=2.0, help="safety factor on the measured peaks (default 2)")
    args = parser.parse_args(argv)
    import yaml

    run = Path(args.run)
    params = yaml.safe_load((run / "params.yaml").read_text()) if (run / "params.yaml").is_file() else {}
    peaks = measured(run)
    if not peaks:
        parser.error(f"no timing.json with peak_rss_mb under {run}: run the workflow there first")
    asked = requests(peaks, params, args.data, args.train, args.margin)
    print(f"{'rule':10} {'seconds':>8} {'peak MB':>8} {'worker MB':>9} {'mem_mb':>7} {'runtime':>7}")
    for rule, peak in sorted(peaks.items()):
        print(f"{rule:10} {peak['seconds']:8.1f} {peak['peak_rss_mb']:8.0f} {peak['peak_rss_children_mb']:9.0f} "
              f"{asked[rule]['mem_mb']:7d} {asked[rule]['runtime']:7d}")
    print("\nset-resources:")
    for rule, ask in asked.items():
        print(f"  {rule}:\n    mem_mb: \"{ask['mem_mb']} * attempt\"\n    runtime: \"{ask['runtime']} * attempt\"")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
