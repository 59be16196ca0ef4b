"""The classify stage's classifier file: written by classify, read by score as a feature encoder.

Kept apart from :mod:`vtgen.io.checkpoints`, which imports the translation networks, so that the
score stage's code dependencies do not include them.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import torch


def save_classifier(path: Path, model, classes: list[str], about: dict) -> None:
    """The classify stage's real-only classifier of one modality (the score stage's feature encoder):
    weights, the class names in label order, and how it was built (``model.size``, ``model.width``).
    Written into the stage's atomic output folder, so a plain save is enough."""
    torch.save({"state_dict": model.state_dict(), "classes": list(classes), "size": model.size,
                 "width": model.width, **about}, path)


def load_classifier(path: str | Path):
    """(AlexNet in eval mode, its record) from a file written by :func:`save_classifier`; a ValueError
    naming the file when it is not one."""
    from vtgen.core.classifier import AlexNet

    path = Path(path)
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
        model = AlexNet(len(saved["classes"]), saved["size"], saved["width"])
        model.load_state_dict(saved["state_dict"])
    except (OSError, RuntimeError, KeyError, TypeError, pickle.UnpicklingError) as exc:
        raise ValueError(f"{path}: not a classifier written by the classify stage ({exc}); rerun classify") from exc
    return model.eval(), {k: v for k, v in saved.items() if k != "state_dict"}
