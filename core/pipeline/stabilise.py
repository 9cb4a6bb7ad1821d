"""Stabilisation: how frame 1 is brought into `ref0` before 3D flow compares it with frame 0.

The flow of a pair is meant to show what moved in the scene, not how the camera moved, so frame 1 is
re-lifted straight into ref0 with cam1_T_ref0 = cam1_T_ref1 · inv(ref0_T_ref1). The modes say where
`ref0_T_ref1` comes from:

- "egomotion": the bundle's egomotion estimate (core.pipeline.egomotion), from the images alone;
- "poses": the given poses, ref0_T_ref1 = inv(world_T_ref0) · world_T_ref1, where `ref_t` is
  `world_T_ref_t` when given, else the camera of view 0 at t (docs/conventions.md#frames);
- "none": the identity: frame 1 is taken as seen from ref0, and the flow carries the camera's motion.
"""

from __future__ import annotations

import torch

from core.errors import BundleError, N3dmapError
from core.geometry.poses import ref_pose, relative

STABILISE = ("egomotion", "poses", "none")


def resolve_stabilise(bundle, stabilize: str | None) -> str:
    """The mode to use: `stabilize` itself (checked), or for None the bundle's egomotion estimate when it has
    an egomotion module, else the poses."""
    if stabilize is None:
        return "egomotion" if "egomotion" in bundle.modules else "poses"
    if stabilize not in STABILISE:
        raise N3dmapError(f"stabilize must be one of {STABILISE}, got {stabilize!r}")
    if stabilize == "egomotion" and "egomotion" not in bundle.modules:
        raise BundleError(f"stabilize='egomotion' needs an 'egomotion' module; the bundle holds "
                          f"{sorted(bundle.modules)}")
    return stabilize


def poses_ref0_T_ref1(world_T_cam0: torch.Tensor, world_T_cam1: torch.Tensor,
                      world_T_ref0: torch.Tensor | None = None,
                      world_T_ref1: torch.Tensor | None = None) -> torch.Tensor:
    """world_T_cam0/1 B×V×4×4, world_T_ref0/1 B×4×4 or None -> ref0_T_ref1 B×4×4 from the poses."""
    return relative(ref_pose(world_T_cam0, world_T_ref0), ref_pose(world_T_cam1, world_T_ref1))


def identity_like(world_T_cam: torch.Tensor) -> torch.Tensor:
    """B×4×4 identities on world_T_cam's (B×V×4×4) device and dtype: "none"'s ref0_T_ref1."""
    B = world_T_cam.shape[0]
    return torch.eye(4, dtype=world_T_cam.dtype, device=world_T_cam.device).expand(B, 4, 4).clone()
