"""Model files: the generator file the train stage writes and generate/translate load,
classifier weights a user supplies, and atomic torch saves.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Mapping
from pathlib import Path

import torch

from vtgen.core.device import resolve_device
from vtgen.core.domain import DIRECTIONS
from vtgen.core.models import UNetGenerator


def save_atomic(obj, path: Path) -> None:
    """torch.save to a temporary sibling, then rename. Saving through a file object lets a full disk
    surface as OSError(ENOSPC) naming the file (torch.save to a path hides it in a RuntimeError)."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as handle:
            torch.save(obj, handle)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(tmp)) from exc
    os.replace(tmp, path)


def save_generator(path: Path, generator: UNetGenerator, settings: dict, direction: str, scope: str) -> None:
    """The file `vtgen generate` and `vtgen translate` load: weights plus what is needed to rebuild the network."""
    source_mod, target_mod = DIRECTIONS[direction]
    save_atomic({"state_dict": generator.state_dict(), "settings": settings, "direction": direction, "scope": scope,
                  "input_modality": source_mod, "output_modality": target_mod}, path)


def load_translator(model: str | Path, device: str = "cpu") -> tuple[UNetGenerator, dict]:
    """Load a generator written by the train stage (its folder or its generator.pt), in eval mode."""
    path = Path(model)
    if path.is_dir():
        path = path / "generator.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained generator here (run the train stage first)")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        settings = saved["settings"]
        generator = UNetGenerator(settings["size"], settings["ngf"], settings["kernel"])
        generator.load_state_dict(saved["state_dict"])
    except (KeyError, TypeError, RuntimeError, EOFError, OSError, pickle.UnpicklingError) as exc:
        raise ValueError(f"{path}: not a vtgen generator checkpoint ({exc})") from exc
    meta = {k: saved[k] for k in ("direction", "scope", "input_modality", "output_modality")}
    meta["size"], meta["path"] = settings["size"], str(path)
    return generator.to(resolve_device(device)).eval(), meta


def read_state_dict(path: str | Path) -> Mapping:
    """A user's weights file: ``torch.save(model.state_dict())`` or a dict holding it under ``state_dict``.

    Raises ValueError naming the file when it is missing, unreadable or not a mapping of tensors.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: weights file not found")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises pickle, runtime and zip errors alike for a file it cannot read
        raise ValueError(f"{path}: not a torch state_dict file ({type(exc).__name__}: {exc})") from exc
    if isinstance(state, Mapping) and isinstance(state.get("state_dict"), Mapping):
        state = state["state_dict"]
    if not isinstance(state, Mapping) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ValueError(f"{path}: expected a state_dict (a mapping of names to tensors), got {type(state).__name__}")
    return state


def save_classifier(path: Path, model, classes: list[str], about: dict) -> None:
    """The classify stage's real-only classifier of one modality (the score stage's feature encoder):
    weights, the class names in label order, and how it was built (``model.size``, ``model.width``)."""
    save_atomic({"state_dict": model.state_dict(), "classes": list(classes), "size": model.size,
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
