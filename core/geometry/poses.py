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


# Below this horizontal length of the camera's optical axis (a camera looking nearly straight up or down)
# the heading comes from its x axis instead, which is then close to horizontal.
LEVEL_MIN_HORIZONTAL = 0.1


def levelled(world_T_cam: torch.Tensor) -> torch.Tensor:
    """The camera's gravity-levelled frame: world_T_cam ...×4×4 in a world whose Y points down (gravity)
    -> world_T_level ...×4×4 with the camera's centre as origin, Y = world Y (down), and Z the camera's
    optical axis projected onto the horizontal plane (its heading); X = Y × Z, i.e. right. Pitch and roll
    are dropped, yaw kept: level_T_cam is a rotation about the level's x and z axes only.

    Why: an upright object has a yaw-only box (docs/conventions.md#boxes) only in a frame whose Y is
    vertical, and the map's ground plane is horizontal only there; the synthetic cameras look down ~10°.
    """
    R = world_T_cam[..., :3, :3]  # ...×3×3, columns: the camera's axes in world
    forward, right = R[..., :, 2], R[..., :, 0]  # ...×3 each
    horizontal = torch.linalg.vector_norm(forward[..., [0, 2]], dim=-1)  # ...
    # yaw ψ of the level frame: its Z column is (sin ψ, 0, cos ψ), its X column (cos ψ, 0, −sin ψ)
    yaw_from_forward = torch.atan2(forward[..., 0], forward[..., 2])
    yaw_from_right = torch.atan2(-right[..., 2], right[..., 0])
    yaw = torch.where(horizontal >= LEVEL_MIN_HORIZONTAL, yaw_from_forward, yaw_from_right)  # ...
    world_T_level = torch.zeros_like(world_T_cam)
    world_T_level[..., :3, :3] = se3.yaw_to_matrix(yaw)
    world_T_level[..., :3, 3] = world_T_cam[..., :3, 3]
    world_T_level[..., 3, 3] = 1.0
    return world_T_level


def level_over_ground(world_T_cam: torch.Tensor, *, ahead: float = 0.0, ground_y: float | None = None,
                      origin_height: float = 0.0) -> torch.Tensor:
    """`levelled(world_T_cam)` moved to where a map of the scene in front of the camera belongs:
    `ahead` metres along its heading, and, given the world's ground plane Y = `ground_y` (Y down), at
    `origin_height` metres above the ground (its Y = ground_y − origin_height); without `ground_y` it
    stays at the camera's height. world_T_cam ...×4×4 -> world_T_ref ...×4×4 (axes as `levelled`).

    Why: a camera-centred grid holds what is around the camera; the training grids hold a scene seen
    from 12–20 m away with the ground `Preset.ground_y` below their centre. A camera 5 m up looking at a
    street 18 m ahead leaves the street out of a camera-centred levelled grid (measured: stream recall at
    IoU 0.25 0.21 tilted, 0.12 levelled).
    """
    world_T_ref = levelled(world_T_cam)  # a fresh tensor: safe to move in place
    heading = world_T_ref[..., :3, 2]  # ...×3, horizontal unit vector
    world_T_ref[..., :3, 3] = world_T_ref[..., :3, 3] + float(ahead) * heading
    if ground_y is not None:
        world_T_ref[..., 1, 3] = float(ground_y) - float(origin_height)
    return world_T_ref
