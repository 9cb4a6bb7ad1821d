"""Local negatives for the 3D view-contrastive loss (optional; off by default, not in the paper).

The paper's negatives are drawn across the whole batch (distance-weighted), so a voxel's nearest neighbours
are almost never its negatives and nothing asks features to tell a voxel from the one beside it — which is
what matching a voxel to its moved self needs (flow over frozen features). This term adds, for each sampled
observed voxel p, one negative at a random neighbour q = p + δ (δ ≠ 0, each axis within ±radius, q observed
and in the grid): the margin loss's negative hinge relu(β − ‖top(p) − bottom(q)‖ + α), averaged over its
non-zero terms. Only the contrastive objective has negatives to place, so only it gets the term.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError
from core.losses.contrastive import sample_positions


def neighbour_offsets(count: int, radius: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """count×3 (z, y, x) integer offsets, each axis uniform in [−radius, radius], never all zero."""
    if radius < 1:
        raise ShapeError(f"local negatives need radius >= 1, got {radius}")
    side = 2 * radius + 1
    code = torch.randint(side ** 3 - 1, (count,), generator=generator)  # skip the centre code
    code = code + (code >= (side ** 3) // 2).long()                      # centre = side³ // 2
    return torch.stack([code // (side * side), (code // side) % side, code % side], dim=1) - radius  # count×3


def local_negative_loss(top_down: torch.Tensor, bottom_up: torch.Tensor, valid: torch.Tensor, *, radius: int,
                        samples: int, beta: float = 1.2, margin: float = 0.2,
                        generator: torch.Generator | None = None) -> torch.Tensor:
    """top_down, bottom_up: B×C×Z×Y×X unit features; valid: B×1×Z×Y×X -> scalar (0 with a gradient path when
    no sampled voxel has an observed neighbour)."""
    if top_down.shape != bottom_up.shape or top_down.dim() != 5:
        raise ShapeError(f"top_down {tuple(top_down.shape)} and bottom_up {tuple(bottom_up.shape)} must be the "
                         f"same B×C×Z×Y×X")
    B, C, Z, Y, X = top_down.shape
    ok = valid.reshape(B, -1) > 0.5                                     # B×P
    rows, cols = sample_positions(ok, samples, generator)               # K, K
    if rows.numel() == 0:
        return (top_down.sum() + bottom_up.sum()) * 0.0
    p = torch.stack([cols // (Y * X), (cols // X) % Y, cols % X], dim=1)  # K×3 (z, y, x)
    q = p + neighbour_offsets(rows.numel(), radius, generator).to(p.device)  # K×3
    inside = ((q >= 0) & (q < torch.tensor([Z, Y, X], device=q.device))).all(dim=1)  # K
    q_index = (q[:, 0] * Y + q[:, 1]) * X + q[:, 2]                     # K (garbage where not inside)
    keep = inside.clone()
    keep[inside] = ok[rows[inside], q_index[inside]]
    if not keep.any():
        return (top_down.sum() + bottom_up.sum()) * 0.0
    rows, cols, q_index = rows[keep], cols[keep], q_index[keep]
    anchor = top_down.reshape(B, C, -1)[rows, :, cols].float()          # K'×C
    negative = bottom_up.reshape(B, C, -1)[rows, :, q_index].float()    # K'×C
    d_an = torch.sqrt(((negative - anchor) ** 2).sum(dim=1) + 1e-8)      # K'
    hinge = torch.relu(beta - d_an + margin)
    return hinge.sum() / (hinge > 0).sum().clamp(min=1).to(hinge.dtype)
