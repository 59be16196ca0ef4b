"""Where torch work runs: the device named in params."""

from __future__ import annotations

import torch


def resolve_device(name: str) -> torch.device:
    """auto -> CUDA when available else CPU; cuda without a GPU is an error, not a silent fallback."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("translation.device is 'cuda' but torch sees no CUDA device (use auto or cpu)")
    return torch.device(name)
