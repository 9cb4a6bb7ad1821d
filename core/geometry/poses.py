"""Relative poses from world poses: the one place n3dmap composes `inv(world_T_a) · world_T_b`.

Conventions (docs/conventions.md#poses): `a_T_b` maps points of frame b into frame a
(p_a = a_T_b @ p_b). Records and batches carry poses in `world`: `world_T_cam` per view and
`world_T_ref` (the map frame) per time step. Every transform between two of those frames is
`relative(world_T_a, world_T_b) = inv(world_T_a) · world_T_b` — a camera from the map frame
(`cam_T_ref`), one map frame from another (`ref0_T_ref1`), one camera from another — so one function
holds the order of the product and the rigid inverse.
"""

from __future__ import annotations

import torch

from core.geometry import se3


def relative(world_T_a: torch.Tensor, world_T_b: torch.Tensor) -> torch.Tensor:
    """a_T_b = inv(world_T_a) · world_T_b for rigid poses. ...×4×4 each (leading dims broadcast) -> ...×4×4."""
    return se3.compose(se3.invert(world_T_a), world_T_b)


def ref_pose(world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None) -> torch.Tensor:
    """world_T_ref B×4×4 of one instant: the given one, else the camera of view 0 (world_T_cam B×V×4×4)."""
    return world_T_cam[:, 0] if world_T_ref is None else world_T_ref


def rig_cam_T_ref(world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None) -> torch.Tensor:
    """world_T_cam B×V×4×4, world_T_ref B×4×4 or None (= view 0's camera) -> cam_T_ref B×V×4×4."""
    B, V = world_T_cam.shape[:2]
    return relative(world_T_cam, ref_pose(world_T_cam, world_T_ref)[:, None].expand(B, V, 4, 4))


def camera_centres(cam_T_ref: torch.Tensor) -> torch.Tensor:
    """cam_T_ref ...×4×4 -> ...×3: each camera's centre in ref (the translation of ref_T_cam)."""
    return se3.invert(cam_T_ref)[..., :3, 3]
