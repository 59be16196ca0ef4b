"""Score stage seconds at 1x, 4x and 10x the images, before vs after: the slope in seconds per 1,000 images.

Builds the score stage's inputs in a temporary folder (never under the project) from the real
frames of ``../shared/data/vt60_subset`` (480 touch frames, 240 photos, 10 classes): at scale s,
every frame gives s tiles of 64 px, copy 0 its centre crop, copies 1.. a random crop (55-90% of the
shorter side, anywhere in the frame), a random horizontal flip and a brightness factor in
[0.8, 1.2]. Each copy of an instance is a new instance, and consecutive frames of one instance and
copy form split groups of 6 (the frames are near-duplicates), so every scale keeps the same test
share. Split per class by group: test 20%, val 10%, train the rest. Pairs are class pairs (input
and target drawn from one class and split), as the real data of issue 26 had. The "generated"
images are a STAND-IN: each test input's class-pair target with a Gaussian blur (sigma 1) and
noise (std 8 grey levels), so the sets have the sizes and class structure of a real run, not its
quality. The classifier view reads a real-only AlexNet (the classify defaults: 64 px, width 0.25)
trained here for 2 epochs on the training tiles of the target modality.

The stage (``run_score``) runs with the ``src/`` of a git ref (``--before``) and with the working
tree, alternately in fresh subprocesses (before, after, after, before, ...), so a change in machine
load hits both alike. Prints one markdown table: seconds per scale, the slope (least squares over
the scales, seconds per 1,000 images) of the wall and CPU time (on a loaded machine the CPU time of a
one-thread run is the steadier measure) and the stage's own split of its wall time.

    python benchmarks/score_scaling.py                       # scales 1 4 10, before = BEFORE, 1 round
    python benchmarks/score_scaling.py --scales 1 4 --repeats 2 --before HEAD
    python benchmarks/score_scaling.py --keep /tmp/score_bench   # keep (or reuse) the built inputs
    python benchmarks/score_scaling.py --run /tmp/ms/clone_x10 --before 93f6e00 --repeats 2   # a finished run

With ``--run FOLDER`` nothing is built: the stage reads a finished main job's ``data/pairs``,
``data/generated`` and ``data/classify`` (tile paths relative to FOLDER), before and after alternately
(ABAB), and the table gives each run's wall and CPU seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SOURCE = REPO.parent / "shared" / "data" / "vt60_subset"
BEFORE = "4749d18"  # the commit before the score speed work
SIZE = 64
GROUP_FRAMES = 6
MODALITIES = {"touch": "tactile", "vision": "visual"}

RUNNER = """
import json, sys, time
import torch
sys.path.insert(0, sys.argv[1])
from vtgen.stages.score import run_score
params = {"dataset": {"source": "pattern"}, "score": json.loads(sys.argv[2])}
started, cpu = time.perf_counter(), time.process_time()
summary = run_score(params, sys.argv[3] + "/pairs", sys.argv[3] + "/generated", sys.argv[4], sys.argv[3] + "/classify")
print("BENCH " + json.dumps({"seconds": time.perf_counter() - started, "cpu_seconds": time.process_time() - cpu,
                             "parts": summary.get("seconds", {})}))
"""


def _tile(frame, rng: np.random.Generator, copy: int):
    """One 64 px RGB tile of a PIL frame: the centre crop for copy 0, else a random crop, flip and brightness."""
    from PIL import Image, ImageEnhance

    w, h = frame.size
    short = min(w, h)
    if copy == 0:
        side = short // 2
        x, y = (w - side) // 2, (h - side) // 2
    else:
        side = int(short * rng.uniform(0.55, 0.9))
        x, y = int(rng.integers(0, w - side + 1)), int(rng.integers(0, h - side + 1))
    tile = frame.crop((x, y, x + side, y + side)).resize((SIZE, SIZE), Image.Resampling.BOX)
    if copy:
        if rng.random() < 0.5:
            tile = tile.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
        tile = ImageEnhance.Brightness(tile).enhance(float(rng.uniform(0.8, 1.2)))
    return tile


def build_inputs(root: Path, scale: int, seed: int = 0) -> dict:
    """Write tiles, pairs/{splits,v2t,t2v}.parquet, generated/<direction>/generated.parquet and
    classify/<modality>/encoder.pt for one scale under ``root``; returns counts."""
    import pandas as pd
    import torch
    from PIL import Image, ImageFilter

    rng = np.random.default_rng(seed)
    rows = []
    frames = sorted(p for p in SOURCE.rglob("*.jpg"))
    if not frames:
        raise SystemExit(f"no frames under {SOURCE}: this benchmark needs ../shared/data/vt60_subset")
    for path in frames:
        folder, cls, inst = path.relative_to(SOURCE).parts[:3]
        with Image.open(path) as image:
            frame = image.convert("RGB")
        for copy in range(scale):
            out = root / "tiles" / folder / cls / f"{inst}_{copy}" / (path.stem + ".png")
            out.parent.mkdir(parents=True, exist_ok=True)
            _tile(frame, rng, copy).save(out)
            rows.append({"path": str(out), "class": cls, "modality": MODALITIES[folder], "source": path.name,
                         "instance": f"{cls}/{inst}/{copy}"})
    splits = pd.DataFrame(rows).sort_values("path").reset_index(drop=True)
    splits["frame"] = splits.groupby("instance").cumcount()
    splits["group"] = splits["instance"] + "/" + (splits["frame"] // GROUP_FRAMES).astype(str)
    splits["split"] = "train"
    for (_, _), part in splits.groupby(["class", "modality"]):
        groups = rng.permutation(sorted(part["group"].unique()))
        n_test, n_val = max(1, round(0.2 * len(groups))), max(1, round(0.1 * len(groups)))
        splits.loc[part.index[part["group"].isin(groups[:n_test])], "split"] = "test"
        splits.loc[part.index[part["group"].isin(groups[n_test:n_test + n_val])], "split"] = "val"
    (root / "pairs").mkdir(exist_ok=True)
    splits[["path", "class", "modality", "source", "group", "split"]].to_parquet(root / "pairs/splits.parquet")
    for direction, (source, target) in {"v2t": ("visual", "tactile"), "t2v": ("tactile", "visual")}.items():
        pairs = []
        for (cls, split), part in splits[splits["modality"] == source].groupby(["class", "split"]):
            targets = splits[(splits["modality"] == target) & (splits["class"] == cls) & (splits["split"] == split)]
            drawn = targets["path"].to_numpy()[rng.integers(0, len(targets), len(part))]
            pairs += [{"direction": direction, "split": split, "class": cls, "input_path": i, "target_path": t,
                       "input_source": "", "target_source": "", "aligned": False, "pair_kind": "class"}
                      for i, t in zip(part["path"], drawn)]
        pairs = pd.DataFrame(pairs)
        pairs.to_parquet(root / f"pairs/{direction}.parquet")
        test = pairs[pairs["split"] == "test"]
        out_dir = root / "generated" / direction
        out_dir.mkdir(parents=True, exist_ok=True)
        outputs = []
        for i, (inp, tgt) in enumerate(zip(test["input_path"], test["target_path"])):
            with Image.open(tgt) as image:
                blurred = np.asarray(image.filter(ImageFilter.GaussianBlur(1)), dtype=np.float64)
            noisy = np.clip(blurred + rng.normal(0, 8, blurred.shape), 0, 255).round().astype(np.uint8)
            out = out_dir / f"{i:05d}.png"
            Image.fromarray(noisy).save(out)
            outputs.append(str(out))
        pd.DataFrame({"direction": direction, "scope": "all", "split": "test", "class": test["class"].to_numpy(),
                      "input_path": test["input_path"].to_numpy(), "output_path": outputs,
                      "ground_truth_path": None, "model": "stand-in"}).to_parquet(out_dir / "generated.parquet")
    for modality in ("tactile", "visual"):
        train_classifier(splits[(splits["modality"] == modality) & (splits["split"] == "train")],
                         root / "classify" / modality / "encoder.pt")
    return {"images": len(splits), "test": int((splits["split"] == "test").sum()),
            "train": int((splits["split"] == "train").sum())}


def train_classifier(rows, path: Path, epochs: int = 2) -> None:
    """A real-only AlexNet (classify defaults) trained briefly on ``rows``' tiles, saved as the classify stage does."""
    import torch
    sys.path.insert(0, str(REPO / "src"))
    from vtgen.core.classifier import AlexNet
    from vtgen.io.classifiers import save_classifier
    from vtgen.io.images import read_tiles

    classes = sorted(rows["class"].unique())
    images = read_tiles(list(rows["path"]), SIZE)
    labels = torch.tensor([classes.index(c) for c in rows["class"]])
    torch.manual_seed(0)
    model = AlexNet(len(classes), SIZE, 0.25)
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    for _ in range(epochs):
        for batch in torch.randperm(len(images)).split(64):
            loss = torch.nn.functional.cross_entropy(model(images[batch]), labels[batch])
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_classifier(path, model.eval(), classes, {"note": "benchmark stand-in, 2 epochs"})


def run_once(src: Path, inputs: Path, score_params: dict, threads: int, cwd: Path | None = None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env.update({"OMP_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads),
                "OPENBLAS_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)})
    with tempfile.TemporaryDirectory() as out:
        done = subprocess.run([sys.executable, "-c", RUNNER, str(src), json.dumps(score_params), str(inputs),
                               str(Path(out) / "scores")], capture_output=True, text=True, env=env, cwd=cwd)
    if done.returncode:
        raise SystemExit(f"score run failed ({src}):\n{done.stderr[-3000:]}")
    line = next(x for x in done.stdout.splitlines() if x.startswith("BENCH "))
    return json.loads(line[6:])


COMPILE = """
import sys
sys.path.insert(0, sys.argv[1])
import numpy as np
from vtgen.core.metrics import colour_ssim, grey_ssim, pairwise_colour_ssim
x = np.zeros((2, 16, 16, 3), np.uint8)
colour_ssim(x, x), grey_ssim(x, x), pairwise_colour_ssim(x, x)
"""


def time_run(folder: Path, sources: dict, score_params: dict, threads: int, repeats: int) -> None:
    """``--run``: the stage on a finished run's data, the sources alternately; prints one table."""
    for src in sources.values():  # numba compiles (and caches) each source's kernels once, untimed
        subprocess.run([sys.executable, "-c", COMPILE, str(src)], check=True, capture_output=True)
    runs: dict = {name: [] for name in sources}
    for r in range(repeats):
        for name in (list(sources) if r % 2 == 0 else list(sources)[::-1]):
            load = os.getloadavg()[0]
            result = run_once(sources[name], folder / "data", score_params, threads, cwd=folder)
            runs[name].append({**result, "load": load})
            print(f"{name}: {result['seconds']:.1f} s wall, {result['cpu_seconds']:.1f} s CPU, load {load:.1f} "
                  f"{result['parts']}", file=sys.stderr, flush=True)
    print(f"\nscore stage on {folder}, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{threads} threads, runs alternated\n")
    print("| code | wall s (runs) | CPU s (runs) | load average at each start | SSIM / distribution / memorisation + diversity, s |")
    print("|---|---|---|---|---|")
    for name, results in runs.items():
        parts = " ; ".join(" / ".join(f"{v:.0f}" for v in r["parts"].values()) for r in results)
        cells = [", ".join(f"{r[key]:.1f}" for r in results) for key in ("seconds", "cpu_seconds", "load")]
        print(f"| {name} | " + " | ".join(cells) + f" | {parts} |")


def slope(images: list[int], seconds: list[float]) -> float:
    """Least-squares slope, seconds per 1,000 images."""
    if len(images) < 2:
        return float("nan")
    return float(np.polyfit(np.array(images) / 1000, seconds, 1)[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scales", type=int, nargs="+", default=[1, 4, 10])
    parser.add_argument("--before", default=BEFORE, help="git ref timed as 'before' ('none' to skip)")
    parser.add_argument("--after", default="", help="git ref timed as 'after' (default: the working tree)")
    parser.add_argument("--repeats", type=int, default=1, help="rounds per scale (each: before and after, ABBA)")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch/OpenMP/numba threads of the stage (1: on a shared, loaded machine two threads "
                             "mostly wait for each other)")
    parser.add_argument("--keep", type=Path, help="build (or reuse) the inputs here instead of a temporary folder")
    parser.add_argument("--run", type=Path, help="time the stage on this finished run folder's data/ instead")
    args = parser.parse_args()
    score_params = {"batch_size": 256}
    try:
        import yaml
        score_params = yaml.safe_load((REPO / "params.yaml").read_text())["score"]
    except (ImportError, OSError, KeyError):
        pass
    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        def extract(ref: str, name: str) -> Path:
            archive = subprocess.run(["git", "-C", str(REPO), "archive", ref, "src"], check=True,
                                     capture_output=True).stdout
            (Path(tmp) / name).mkdir()
            subprocess.run(["tar", "-x", "-C", str(Path(tmp) / name)], input=archive, check=True)
            return Path(tmp) / name / "src"

        sources = {"after": extract(args.after, "after") if args.after else REPO / "src"}
        if args.before != "none":
            sources = {"before": extract(args.before, "before"), **sources}
        if args.run:
            time_run(args.run.resolve(), sources, score_params, args.threads, args.repeats)
            return
        results: dict = {}
        for scale in args.scales:
            inputs = base / f"x{scale}"
            counts_file = inputs / "counts.json"
            if not counts_file.is_file():
                inputs.mkdir(parents=True, exist_ok=True)
                counts_file.write_text(json.dumps(build_inputs(inputs, scale)))
            counts = json.loads(counts_file.read_text())
            order = list(sources)
            if scale == args.scales[0]:  # warm-up, not timed: numba compiles each source's SSIM kernel once
                for name in order:
                    run_once(sources[name], inputs, score_params, args.threads)
            for r in range(args.repeats):
                for name in (order if r % 2 == 0 else order[::-1]):
                    result = run_once(sources[name], inputs, score_params, args.threads)
                    results.setdefault((scale, name), []).append(result)
                    print(f"x{scale} ({counts['images']} images) {name}: {result['seconds']:.1f} s wall, "
                          f"{result['cpu_seconds']:.1f} s CPU {result['parts']}", file=sys.stderr, flush=True)
            results[scale] = counts
    print(f"\nscore stage, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"{args.threads} threads, load average at the end {os.getloadavg()[0]:.1f}; "
          f"median of {args.repeats} round(s); inputs built from vt60_subset (generated = STAND-IN)\n")
    images = [results[s]["images"] for s in args.scales]
    print("| code | measure | " + " | ".join(f"x{s}: {results[s]['images']} images ({results[s]['test']} test)"
                                              for s in args.scales) + " | slope, s per 1,000 images |")
    print("|---|---|" + "---|" * (len(args.scales) + 1))
    for name in sources:
        for measure in ("seconds", "cpu_seconds"):
            medians = [float(np.median([r[measure] for r in results[(s, name)]])) for s in args.scales]
            cells = [f"{m:.1f} s" for m in medians]
            print(f"| {name} | {'wall' if measure == 'seconds' else 'CPU'} | " + " | ".join(cells)
                  + f" | {slope(images, medians):.2f} |")
        parts = [results[(s, name)][0]["parts"] for s in args.scales]
        print(f"| {name} | wall by part | " + " | ".join(", ".join(f"{k} {v:.0f}" for k, v in p.items()) for p in parts)
              + " | |")


if __name__ == "__main__":
    main()
