"""Local matching loss: a voxel's feature must find its own content again after that content moved.

3D flow over feature maps compares each voxel's feature at t with the features within a few voxels of
it at t+1 (core.models.flow3d's cost volumes). That only works when the best match in such a window is
where the content went. The view-contrastive objective alone does not ask for it: its negatives are
random voxels of the batch, almost never the neighbours, and measured on the small preset
(tests/benchmarks/bench_flow_features.py) moving only an object's input voxels by 1-3 voxels left
each moved voxel's feature closer to what now sat at its old place than to itself at the new one.

Given two feature volumes of the same scene before and after a known motion (flow t -> t+1 in voxels),
for sampled voxels p this is the cross-entropy of a softmax over the window of displacements δ
(|δ| ≤ radius per axis, inside the grid) of cos(f0(p), f1(p + flow(p) + δ)) / temperature, with δ = 0 the target:
InfoNCE whose negatives are the true match's neighbours, i.e. exactly the candidates a cost volume sees.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.errors import ShapeError, check_shape
from core.geometry.resample import sample_volume_at
from core.losses.contrastive import sample_positions
from core.models.cost_volume import displacements


def local_matching_loss(f0: torch.Tensor, f1: torch.Tensor, flow: torch.Tensor, valid: torch.Tensor, *,
                        radius: tuple[int, int, int] = (2, 1, 2), temperature: float = 0.1,
                        samples: int = 256, generator: torch.Generator | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """f0, f1: B×F×Z×Y×X features (any length; compared by cosine); flow: B×3×Z×Y×X (x, y, z) voxels
    with f1(p + flow(p)) the content of f0(p); valid: B×1×Z×Y×X where to sample p.

    Returns (loss: scalar mean cross-entropy over the sampled voxels whose match lies inside the grid,
    hit: the share of them whose best-scoring δ is 0). Both are 0 (loss with a zero gradient path) when
    nothing valid is left.
    """
    check_shape("f0", f0, (None, None, None, None, None))
    check_shape("f1", f1, tuple(f0.shape))
    B, C, Z, Y, X = f0.shape
    check_shape("flow", flow, (B, 3, Z, Y, X))
    check_shape("valid", valid, (B, 1, Z, Y, X))
    if temperature <= 0:
        raise ShapeError(f"local_matching_loss: temperature must be positive, got {temperature}")
    rows, cols = sample_positions(valid.reshape(B, -1) > 0.5, samples, generator)  # K, K
    zero = (f0.sum() + f1.sum()) * 0.0
    if rows.numel() == 0:
        return zero, zero.detach()
    z, y, x = cols // (Y * X), (cols // X) % Y, cols % X  # K each
    p = torch.stack([x, y, z], dim=1).to(f0.dtype)  # K×3 (x, y, z) mem
    target = p + flow[rows, :, z, y, x].to(f0.dtype)  # K×3 where p's content went
    size_xyz = torch.tensor([X, Y, Z], dtype=f0.dtype, device=f0.device)
    inside = ((target >= 0) & (target <= size_xyz - 1)).all(dim=1)  # K
    d = displacements(radius, device=f0.device, dtype=f0.dtype)  # D×3, z-major; δ = 0 in the middle
    centre = d.shape[0] // 2
    anchors = F.normalize(f0[rows, :, z, y, x].float(), dim=1)  # K×F
    losses, hits = [], []
    for b in range(B):
        keep = (rows == b) & inside  # K
        if not keep.any():
            continue
        where = target[keep][:, None, :] + d[None]  # Kb×D×3
        cand = sample_volume_at(f1[b:b + 1], where.reshape(1, -1, d.shape[0], 1, 3))[0, :, :, :, 0].float()  # F×Kb×D
        cand = F.normalize(cand, dim=0)
        logits = torch.einsum("kf,fkd->kd", anchors[keep], cand) / temperature  # Kb×D
        # Candidates outside the grid are no candidates (their samples are ~0, not a feature).
        logits = logits.masked_fill(((where < 0) | (where > size_xyz - 1)).any(dim=-1), float("-inf"))
        labels = torch.full((logits.shape[0],), centre, dtype=torch.long, device=logits.device)
        losses.append(F.cross_entropy(logits, labels, reduction="none"))
        hits.append((logits.argmax(dim=1) == centre).float())
    if not losses:
        return zero, zero.detach()
    return torch.cat(losses).mean(), torch.cat(hits).mean().detach()
