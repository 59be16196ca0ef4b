"""Model files: the generator file the train stage writes and generate/translate load,
classifier weights a user supplies, and atomic torch saves.
"""

from __future__ import annotations

import errno
import os
import pickle
import shutil
from collections.abc import Mapping
from pathlib import Path

import torch

from vtgen.core.conditioning import Conditioning
from vtgen.core.device import resolve_device
from vtgen.core.domain import DIRECTIONS
from vtgen.core.models import build_generator


LOW_SPACE_BYTES = 64 * 2**20
"""Free space below which a failed torch save is taken for a full disk (:func:`save_atomic`)."""


def save_atomic(obj, path: Path) -> None:
    """torch.save to a temporary sibling, then rename. Saving through a file object lets a full disk
    surface as OSError(ENOSPC) naming the file (torch.save to a path hides it in a RuntimeError); when the disk
    fills up mid-file torch's zip writer still raises RuntimeError ("unexpected pos"), so a RuntimeError with
    less than ``LOW_SPACE_BYTES`` free there is reported as ENOSPC too. The partial file is removed."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as handle:
            torch.save(obj, handle)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise OSError(exc.errno, exc.strerror, str(tmp)) from exc
    except RuntimeError as exc:
        full = shutil.disk_usage(tmp.parent).free < LOW_SPACE_BYTES
        tmp.unlink(missing_ok=True)
        if full:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp)) from exc
        raise RuntimeError(f"{tmp}: {exc}") from exc
    os.replace(tmp, path)


ROI_KEYS = ("size", "tactile_box", "remove_markers", "visual_crop", "crop_fraction")
"""The params.yaml ``roi`` keys a model file records: the rule that cut its training tiles."""


def input_channels(*batches: torch.Tensor) -> tuple[int, str]:
    """(1 or 3, how it was decided) for uint8 N x 3 x S x S input tiles.

    The roi stage writes every tile as RGB, replicating a greyscale source to three equal
    channels; so the sources were greyscale (1) when every tile has R = G = B, colour (3)
    otherwise. With no tiles the answer is unknown and 3 is returned, saying so.
    """
    count = sum(len(b) for b in batches)
    if count == 0:
        return 3, "unknown (no input tiles); 3 recorded"
    grey = all(bool(torch.equal(b[:, 0], b[:, 1]) and torch.equal(b[:, 1], b[:, 2])) for b in batches if len(b))
    return (1, f"R = G = B in all {count} input tiles") if grey else (3, f"colour in the {count} input tiles")


def input_preparation(roi: Mapping, direction: str, model_size: int, *input_tiles: torch.Tensor) -> dict:
    """What `vtgen translate` must do to a raw image before this model sees it.

    ``input_modality`` (the direction's source), ``roi`` (the ROI rule that cut the training
    tiles, ``ROI_KEYS`` of params.yaml's ``roi`` section), ``model_size`` (tiles of ``roi.size``
    are resized to it) and ``input_channels`` (1: greyscale sources, 3: colour; see
    :func:`input_channels`) with ``input_channels_from``.
    """
    missing = [k for k in ROI_KEYS if k not in roi]
    if missing:
        raise ValueError(f"roi section lacks {', '.join(missing)}")
    rule = {k: roi[k] for k in ROI_KEYS}
    if not isinstance(rule["tactile_box"], str):
        rule["tactile_box"] = [int(v) for v in rule["tactile_box"]]
    channels, how = input_channels(*input_tiles)
    return {"input_modality": DIRECTIONS[direction][0], "roi": rule, "model_size": int(model_size),
            "input_channels": channels, "input_channels_from": how}


def save_generator(path: Path, generator: torch.nn.Module, settings: dict, direction: str, scope: str,
                   preparation: dict | None = None, conditioning: Conditioning | None = None) -> None:
    """The file `vtgen generate` and `vtgen translate` load: weights plus what is needed to rebuild the network,
    (from :func:`input_preparation`) how a raw image becomes this model's input, and its conditioning."""
    source_mod, target_mod = DIRECTIONS[direction]
    record = {"state_dict": generator.state_dict(), "settings": settings, "direction": direction, "scope": scope,
              "input_modality": source_mod, "output_modality": target_mod,
              "conditioning": (conditioning or Conditioning()).record()}
    if preparation is not None:
        record["preparation"] = preparation
    save_atomic(record, path)


def _checked_preparation(saved: dict, size: int, path: Path) -> dict | None:
    preparation = saved.get("preparation")
    if preparation is None:
        return None
    roi = preparation.get("roi") if isinstance(preparation, dict) else None
    if (not isinstance(roi, dict) or any(k not in roi for k in ROI_KEYS)
            or preparation.get("input_channels") not in (1, 3) or preparation.get("model_size") != size
            or preparation.get("input_modality") != saved["input_modality"]):
        raise ValueError(f"{path}: its recorded input preparation is damaged ({preparation!r}); retrain the model")
    return preparation


def load_translator(model: str | Path, device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    """Load a generator written by the train stage (its folder or its generator.pt), in eval mode.

    The record holds direction, scope, input_modality, output_modality, size, path, objective (the
    train stage's: pix2pix or class_gan),
    ``conditioning`` (a :class:`Conditioning`; ``none`` for files from before it existed) and
    ``preparation`` (see :func:`input_preparation`), which is None for model files written before
    it was recorded; ``note`` then says so (and is "" otherwise).
    """
    path = Path(model)
    if path.is_dir():
        path = path / "generator.pt"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained generator here (run the train stage first)")
    try:
        saved = torch.load(path, map_location="cpu", weights_only=False)
        settings = saved["settings"]
        conditioning = Conditioning.from_record(saved.get("conditioning"))
        generator = build_generator(settings, 3 + conditioning.extra_channels)
        generator.load_state_dict(saved["state_dict"])
        meta = {k: saved[k] for k in ("direction", "scope", "input_modality", "output_modality")}
        meta["conditioning"] = conditioning
    except (KeyError, TypeError, RuntimeError, EOFError, OSError, pickle.UnpicklingError) as exc:
        raise ValueError(f"{path}: not a vtgen generator checkpoint ({exc})") from exc
    meta["size"], meta["path"] = settings["size"], str(path)
    meta["objective"] = settings.get("objective", "pix2pix")
    meta["preparation"] = _checked_preparation(saved, settings["size"], path)
    meta["note"] = "" if meta["preparation"] else (
        f"{path}: no input preparation recorded (a model file from before it was); inputs must be "
        f"{settings['size']}x{settings['size']} tiles cut like its training tiles")
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

