"""GPU check: the CUDA path of the training step and of the classifier, with seconds per step and images per second.

For a lent GPU machine (the project never needs one). Prints one markdown table per part:

* **translation step** - ``TranslatorTraining.step`` of params.yaml's ``fast`` preset (pix2pix and the
  class-paired ``class_gan`` objective with params.yaml's ``translation.class_gan``, 10 classes, also with
  ``nearest`` 10 over 8 draws) and
  ``paper`` preset, fp32 and bf16 autocast, on in-memory random batches: median seconds per step over
  ``--steps`` steps after ``--warmup`` (CUDA synchronised per step), and the losses' finiteness;
* **classifier** - ``train_classifier`` (the classify stage's AlexNet, params.yaml's ``classify``
  section) for ``--epochs`` epochs on random uint8 tiles of the size of the 10x scaling run's tactile job
  (3,360 training, 960 test tiles, 10 classes): training and evaluation images per second, fp32 and
  bf16. Random tiles: the accuracies say nothing; only the speed does;
* **classifier switches** - the same classifier under ``lr_schedule`` constant and cosine and with
  ``average_epochs`` 3 (weight averaging, batch-norm statistics recomputed on the device), fp32 and bf16, on
  separable colour tiles: each run should read the 60 test tiles and keep its batch-norm statistics finite.

    python benchmarks/gpu_check.py                 # on the GPU machine, from the repository root
    python benchmarks/gpu_check.py --device cpu --steps 5 --warmup 2 --epochs 1   # the same code on a CPU
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
import yaml

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

from vtgen.core.classifier import train_classifier  # noqa: E402
from vtgen.core.translator import TranslatorTraining  # noqa: E402
from vtgen.stages.train import objective_settings  # noqa: E402

CLASSES = 10


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def step_seconds(settings: dict, device: torch.device, precision: str, steps: int, warmup: int) -> tuple[float, bool]:
    """Median seconds of one training step, and whether every loss stayed finite."""
    torch.manual_seed(0)
    class_gan = settings.get("objective") == "class_gan"
    training = TranslatorTraining(settings, device, precision, num_classes=CLASSES if class_gan else 0)
    size, batch = settings["size"], settings["batch_size"] + settings["batch_size"] % 2
    x = torch.rand(batch, 3, size, size, device=device) * 2 - 1
    y = torch.rand(batch, 3, size, size, device=device) * 2 - 1
    labels = torch.arange(batch, device=device) // 2 % CLASSES
    times, finite = [], True
    for i in range(warmup + steps):
        _sync(device)
        started = time.perf_counter()
        losses = training.step(x, y, labels) if class_gan else training.step(x, y)
        _sync(device)
        if i >= warmup:
            times.append(time.perf_counter() - started)
    finite = all(bool(torch.isfinite(v).all()) for v in losses.values())
    return statistics.median(times), finite


def classifier_speed(cfg: dict, device: torch.device, precision: str, epochs: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    size = cfg["size"]
    train_x = torch.randint(0, 256, (3360, 3, size, size), dtype=torch.uint8, generator=generator)
    train_y = torch.randint(0, CLASSES, (3360,), generator=generator)
    test_x = torch.randint(0, 256, (960, 3, size, size), dtype=torch.uint8, generator=generator)
    test_y = torch.randint(0, CLASSES, (960,), generator=generator)
    settings = dict(cfg, epochs=epochs)
    started = time.perf_counter()
    run = train_classifier(train_x, train_y, test_x, test_y, CLASSES, settings, seed=0, device=device,
                           precision=precision)
    return {"seconds": time.perf_counter() - started, "train_per_s": run.train_images / run.train_seconds,
            "eval_per_s": run.eval_images / run.eval_seconds, "final_loss": run.train_loss[-1]}


def colour_tiles(per_class: int, classes: int, size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Separable uint8 tiles: class k is one mean colour per class plus Gaussian noise (std 25 grey levels)."""
    images, labels = [], []
    for k in range(classes):
        colour = torch.tensor([(37 * k) % 256, (91 * k + 40) % 256, (151 * k + 80) % 256], dtype=torch.float32)
        noisy = colour.view(1, 3, 1, 1) + 25 * torch.randn(per_class, 3, size, size, generator=generator)
        images.append(noisy.clamp(0, 255).to(torch.uint8))
        labels += [k] * per_class
    return torch.cat(images), torch.tensor(labels)


def classifier_switches(cfg: dict, device: torch.device, epochs: int) -> list[dict]:
    """``train_classifier`` under each learning-rate schedule and with weight averaging (its batch-norm statistics
    recomputed on ``device``), fp32 and bf16, on separable tiles (6 classes, 240 training and 60 test): every run
    should read the test tiles and keep its batch-norm statistics finite."""
    generator = torch.Generator().manual_seed(0)
    train_x, train_y = colour_tiles(40, 6, cfg["size"], generator)
    test_x, test_y = colour_tiles(10, 6, cfg["size"], generator)
    rows = []
    for schedule, average in (("constant", 0), ("cosine", 0), ("cosine", 3)):
        for precision in ("fp32", "bf16"):
            settings = dict(cfg, epochs=max(epochs, average + 1), lr_schedule=schedule, average_epochs=average)
            run = train_classifier(train_x, train_y, test_x, test_y, 6, settings, seed=0, device=device,
                                   precision=precision)
            statistics_ = [b for name, b in run.model.state_dict().items() if "running" in name]
            rows.append({"schedule": schedule, "average": average, "precision": precision,
                         "accuracy": run.test_accuracy[-1],
                         "finite": bool(statistics_) and all(bool(torch.isfinite(b).all()) for b in statistics_)})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--epochs", type=int, default=3)
    args = parser.parse_args()
    device = torch.device(args.device)
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"torch {torch.__version__}, {name}, bf16 supported: "
          f"{torch.cuda.is_bf16_supported() if device.type == 'cuda' else 'n/a'}\n")

    fast, paper = params["presets"]["fast"], params["presets"]["paper"]
    variants = {"fast, pix2pix": fast,
                "fast, class_gan": objective_settings(fast, params["translation"], "class_gan", "v2t"),
                "fast, class_gan, nearest 10 (8 draws)": dict(objective_settings(fast, params["translation"], "class_gan", "v2t"),
                                                              nearest=10.0, nearest_draws=8),
                "paper, pix2pix": paper}
    print("| preset, objective | batch | precision | s/step (median) | images/s | losses finite |")
    print("|---|---|---|---|---|---|")
    for label, settings in variants.items():
        for precision in ("fp32", "bf16"):
            seconds, finite = step_seconds(settings, device, precision, args.steps, args.warmup)
            batch = settings["batch_size"] + settings["batch_size"] % 2
            print(f"| {label} | {batch} | {precision} | {seconds:.4f} | {batch / seconds:.0f} | {finite} |", flush=True)

    cfg = params["classify"]
    print(f"\nclassifier: {cfg['size']} px, width {cfg['width']}, batch {cfg['batch_size']}, {args.epochs} epochs, "
          "3,360 training and 960 test tiles (random)\n")
    print("| precision | seconds | training images/s | evaluation images/s | last loss |")
    print("|---|---|---|---|---|")
    for precision in ("fp32", "bf16"):
        r = classifier_speed(cfg, device, precision, args.epochs)
        print(f"| {precision} | {r['seconds']:.1f} | {r['train_per_s']:.0f} | {r['eval_per_s']:.0f} | "
              f"{r['final_loss']:.3f} |", flush=True)

    print(f"\nclassifier switches: separable colour tiles, 6 classes, 240 training and 60 test, {max(args.epochs, 4)} "
          "epochs\n")
    print("| lr_schedule | average_epochs | precision | test accuracy (n 60) | batch-norm statistics finite |")
    print("|---|---|---|---|---|")
    for r in classifier_switches(cfg, device, max(args.epochs, 4)):
        print(f"| {r['schedule']} | {r['average']} | {r['precision']} | {r['accuracy']:.3f} | {r['finite']} |", flush=True)


if __name__ == "__main__":
    main()
