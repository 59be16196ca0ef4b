"""Resource limits checked before a run hits them: a batch larger than the data, a run that would not fit in memory.

The memory estimate of a training step was measured on this project's pix2pix networks (2026-11-25, CPU,
fp32, torch 2.13, 1 thread: peak RSS of ``TranslatorTraining.step`` twice on random tensors, batch 4-256,
sizes 64 and 128, widths 16-64): about (1 + 0.1 x width) MB per image of the batch at 64 px, growing with the
pixel count, on top of about 0.5 GB for the process and 16 bytes per weight (weights, gradients, two Adam
moments). It is meant to catch settings that are off by an order of magnitude, not to budget the last GB.
"""

from __future__ import annotations

import re
from pathlib import Path

PROCESS_BYTES = 0.5e9


def available_memory() -> int | None:
    """Bytes of memory available to new allocations (MemAvailable of /proc/meminfo), None where unknown."""
    try:
        match = re.search(r"^MemAvailable:\s+(\d+) kB", Path("/proc/meminfo").read_text(), flags=re.M)
    except OSError:
        return None
    return int(match[1]) * 1024 if match else None


def training_bytes(settings: dict) -> float:
    """Estimated peak memory of one training step on the CPU with ``settings`` (a presets block)."""
    width = max(settings["ngf"], settings["ndf"])
    per_image = (1 + 0.1 * width) * 1e6 * (settings["size"] / 64) ** 2
    # U-Net weights: about 8 x 8 x width^2 x kernel^2 per level pair at the widest levels, doubled for D
    weights = 2 * 8 * 8 * width ** 2 * settings["kernel"] ** 2 * max(1, settings["size"].bit_length() - 1)
    return PROCESS_BYTES + settings["batch_size"] * per_image + 16 * weights


def check_training_fits(settings: dict, training_pairs: int, key: str, label: str, device: str = "cpu",
                        available: int | None = None) -> dict:
    """``settings`` for training on ``training_pairs`` pairs: the batch capped at the number of pairs (with a
    printed line naming ``key``), after refusing (ValueError naming ``key``) a step that would not fit in the
    available memory. ``label`` names the job in messages; only CPU memory is checked."""
    batch = settings["batch_size"]
    if 0 < training_pairs < batch:
        print(f"{label}: {key}.batch_size {batch} is larger than the {training_pairs} training pairs; "
              f"using batch {training_pairs}")
        settings = {**settings, "batch_size": training_pairs}
    available = available_memory() if available is None else available
    if device == "cpu" and available is not None:
        needed = training_bytes(settings)
        if needed > available:
            raise ValueError(
                f"{key}: a training step at batch {settings['batch_size']}, {settings['size']} px and width "
                f"{max(settings['ngf'], settings['ndf'])} needs about {needed / 1e9:.1f} GB, more than the "
                f"{available / 1e9:.1f} GB of memory available; lower {key}.batch_size, size, ngf or ndf")
    return settings
