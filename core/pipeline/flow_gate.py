"""The occupancy gate of 3D flow: which voxels keep their estimated motion at test time.

The paper's rule: flow of every voxel the occupancy head calls free is set to zero (air does not move).
Its cost here, measured: the head calls free the unobserved inside of a moving object (no depth point ever
lands there), and on the small test records that is about half of the voxels of the moving boxes (39 % of the
moving voxels since session 24's ground truth also moves the voxels holding only an object's surface: 2 479 of
6 409 on 16 records), whose flow the gate then zeroes though the raw flow there is mostly right (flow over ±3
features, seed 0, before that fix: moving-voxel L1 EPE raw 0.82 × zero motion, gated 0.89 ×; over the
gated-off half alone raw 0.86 ×, gated 1.0 ×).

`fill` > 0 adds one amodal step to the rule: a voxel called free keeps its flow when it lies within `fill`
voxels (a (2·fill+1)³ box) of an occupied voxel whose gated flow is longer than `moving` voxels — the unseen
side of a moving surface moves with it; free voxels near static surfaces stay zeroed.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.errors import check_shape

GATE_FILL = 0  # the pipelines' default `fill` (core.pipeline.flow.flow_step)


def gate_flow(raw: torch.Tensor, occupancy: torch.Tensor, *, threshold: float = 0.5, fill: int = 0,
              moving: float = 0.5) -> torch.Tensor:
    """raw: B×3×Z×Y×X flow (voxels); occupancy: B×1×Z×Y×X probabilities -> B×3×Z×Y×X, zero where the
    gate is closed. threshold: P(occupied) at or above which a voxel is occupied; fill: voxels (per axis) a
    moving occupied voxel opens the gate around it (0: the paper's rule); moving: L2 length (voxels) above
    which an occupied voxel's flow counts as moving."""
    check_shape("raw", raw, (None, 3, None, None, None))
    check_shape("occupancy", occupancy, (raw.shape[0], 1, *raw.shape[2:]))
    if fill < 0:
        raise ValueError(f"gate_flow: fill must be >= 0 voxels, got {fill}")
    gate = (occupancy >= threshold).to(raw.dtype)  # B×1×Z×Y×X
    if fill:
        moving_occupied = ((raw * gate).norm(dim=1, keepdim=True) > moving).to(raw.dtype)  # B×1×Z×Y×X
        gate = torch.maximum(gate, F.max_pool3d(moving_occupied, 2 * fill + 1, stride=1, padding=fill))
    return raw * gate
