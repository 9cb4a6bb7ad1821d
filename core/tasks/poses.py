"""Camera-from-ref transforms of a batch (docs/conventions.md#poses naming: p_a = a_T_b @ p_b).

`cam_T_ref(batch, t_cam, t_ref)` lifts the views of time `t_cam` into the map frame `ref` of time
`t_ref`: inv(world_T_cam[t_cam]) · world_T_ref[t_ref]. With t_cam = t_ref this only uses the rig
calibration; across times it registers (stabilises) frame t_cam into ref of t_ref with the poses.
"""

from __future__ import annotations

import torch

from core.geometry.poses import relative, rig_cam_T_ref


def cam_T_ref(batch: dict[str, torch.Tensor], t_cam: int, t_ref: int) -> torch.Tensor:
    """batch world_T_cam B×T×V×4×4, world_T_ref B×T×4×4 -> B×V×4×4."""
    return rig_cam_T_ref(batch["world_T_cam"][:, t_cam], batch["world_T_ref"][:, t_ref])


def ref0_T_ref1(batch: dict[str, torch.Tensor], t0: int, t1: int) -> torch.Tensor:
    """Ground-truth egomotion between the map frames of times t0 and t1: B×4×4 (frame ref_t0)."""
    return relative(batch["world_T_ref"][:, t0], batch["world_T_ref"][:, t1])
