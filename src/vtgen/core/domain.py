"""The two modalities and the two translation directions."""

MODALITIES = ("visual", "tactile")
# direction -> (input modality, output modality)
DIRECTIONS = {"v2t": ("visual", "tactile"), "t2v": ("tactile", "visual")}
