"""The two modalities and the two translation directions."""

MODALITIES = ("visual", "tactile")
# direction -> (input modality, output modality)
DIRECTIONS = {"v2t": ("visual", "tactile"), "t2v": ("tactile", "visual")}


def direction_producing(modality: str) -> str:
    """The translation direction whose output is ``modality`` (tactile <- v2t, visual <- t2v)."""
    for direction, (_, target) in DIRECTIONS.items():
        if target == modality:
            return direction
    raise ValueError(f"unknown modality '{modality}' (allowed: {', '.join(t for _, t in DIRECTIONS.values())})")
