"""PatchNCE: an output patch must be told apart, among the patches of its own image, as the one at the place
its input patch was (Park et al. 2020, "Contrastive learning for unpaired image-to-image translation", eq. 2-5).

Where an input and its translation share structure (a fabric's weave seen and felt), this keeps the structure
without asking the output to look like any particular target: no pixel loss to a partner, so no class mean.
The features are the generator's own encoder levels (:meth:`vtgen.core.models.UNetGenerator.encode`), applied to
the input and to the output; a small MLP per level maps each patch's feature vector to a unit vector.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


class PatchProjection(nn.Module):
    """One two-layer MLP per encoder level (Linear, ReLU, Linear to ``dim``), applied to each patch's feature
    vector (CUT's H_l). ``channels``: the feature channels of each level used."""

    def __init__(self, channels: list[int], dim: int = 64) -> None:
        super().__init__()
        self.mlps = nn.ModuleList(nn.Sequential(nn.Linear(c, dim), nn.ReLU(), nn.Linear(dim, dim)) for c in channels)

    def forward(self, level: int, vectors: torch.Tensor) -> torch.Tensor:
        """Unit vectors (… x dim) of the patch feature ``vectors`` (… x channels) of ``level``."""
        return F.normalize(self.mlps[level](vectors), dim=-1)


def patch_nce_loss(query_maps: list[torch.Tensor], key_maps: list[torch.Tensor], projection: PatchProjection,
                   patches: int = 64, temperature: float = 0.07) -> torch.Tensor:
    """Mean over levels l of the InfoNCE loss of Park et al. 2020 (eq. 3): for P locations drawn without
    replacement (the same for every image of the batch, from torch's global generator), with q_i and k_j the
    projected unit vectors of the output's (``query_maps``) and the input's (``key_maps``, detached) features at
    locations i and j of one image,  −log( exp(q_i·k_i/τ) / Σ_j exp(q_i·k_j/τ) ), averaged over i and images;
    negatives come from the same image only. Each map is N x C_l x H_l x W_l; P = min(``patches``, H_l·W_l)."""
    if len(query_maps) != len(key_maps) or not query_maps:
        raise ValueError(f"PatchNCE needs one key map per query map, got {len(query_maps)} and {len(key_maps)}")
    losses = []
    for level, (query, key) in enumerate(zip(query_maps, key_maps)):
        if query.shape != key.shape:
            raise ValueError(f"PatchNCE level {level}: query {tuple(query.shape)} and key {tuple(key.shape)} differ")
        n, c, h, w = query.shape
        where = torch.randperm(h * w)[:min(patches, h * w)].to(query.device)
        q = projection(level, query.flatten(2).transpose(1, 2)[:, where].float())  # N x P x D
        k = projection(level, key.detach().flatten(2).transpose(1, 2)[:, where].float())
        logits = torch.bmm(q, k.transpose(1, 2)) / temperature  # N x P x P, positives on the diagonal
        target = torch.arange(logits.shape[1], device=logits.device).repeat(n)
        losses.append(F.cross_entropy(logits.flatten(0, 1), target))
    return torch.stack(losses).mean()
