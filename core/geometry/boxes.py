"""Canonical oriented 3D boxes and their KITTI conversion.

Conventions (docs/conventions.md#boxes):
- Frames: `cam` / `ref` / `world` are camera-like (X right, Y down, Z forward, metres); every function
  returns boxes in the frame its inputs were in, and callers name that frame (`boxes_ref`, `boxes_cam`).
- A box row is (x, y, z, lx, ly, lz, yaw): the CENTRE (not the bottom), lengths along the object's own
  axes (lx = length, ly = height, lz = width) and yaw in radians about the frame's Y (down) axis with
  R = [[c, 0, s], [0, 1, 0], [-s, 0, c]] (positive yaw turns +x toward −z; the same as KITTI's `ry`).
- The object frame `obj` has its origin at the box centre and its axes along (lx, ly, lz);
  p_frame = box_T_obj @ p_obj. Poses are 4×4 `a_T_b` with p_a = a_T_b @ p_b.
- KITTI labels (camera-2 rectified frame) give the BOTTOM centre (x, y, z), dimensions h, w, l and ry;
  here a KITTI box is a row (h, w, l, x, y, z, ry) in the label file's column order, and
  centre_y = bottom_y − h/2 (Y points down), lx = l, ly = h, lz = w, yaw = ry.
Shapes are B×K×7 (any leading dims work). Device and dtype follow the inputs.
"""

from __future__ import annotations

import torch

from core.errors import N3dmapError, ShapeError
from core.geometry import se3
from core.precision import full_precision

# Corner sign pattern, (x, y, z) in units of half-lengths. Corners 0-3 go round the top face (y = −ly/2,
# up, since Y points down), corners 4-7 round the bottom face; corner i + 4 lies below corner i.
# Their (x, z) coordinates 0-3 trace the bird's-eye-view rectangle in cyclic order.
_CORNER_SIGNS = ((-1, -1, -1), (1, -1, -1), (1, -1, 1), (-1, -1, 1),
                 (-1, 1, -1), (1, 1, -1), (1, 1, 1), (-1, 1, 1))


class NotYawRotationError(N3dmapError, ValueError):
    """A transform applied to boxes rotates about an axis other than Y (yaw-only boxes cannot follow it)."""


def _check_boxes(name: str, boxes: torch.Tensor) -> None:
    if not isinstance(boxes, torch.Tensor) or boxes.dim() < 1 or boxes.shape[-1] != 7:
        shape = "×".join(map(str, getattr(boxes, "shape", ()))) or type(boxes).__name__
        raise ShapeError(f"{name}: expected boxes …×7 (x, y, z, lx, ly, lz, yaw), got {shape}")


def box_T_obj(boxes: torch.Tensor) -> torch.Tensor:
    """Object frame -> the boxes' frame. boxes: B×K×7 -> B×K×4×4 ([yaw rotation | centre])."""
    _check_boxes("boxes", boxes)
    return se3.from_rt(se3.yaw_to_matrix(boxes[..., 6]), boxes[..., :3])


@full_precision
def box_corners(boxes: torch.Tensor) -> torch.Tensor:
    """The 8 corners of each box in the boxes' frame. boxes: B×K×7 -> B×K×8×3 (order: see _CORNER_SIGNS)."""
    _check_boxes("boxes", boxes)
    signs = torch.tensor(_CORNER_SIGNS, dtype=boxes.dtype, device=boxes.device)  # 8×3
    local = 0.5 * signs * boxes[..., None, 3:6]  # B×K×8×3 in obj
    R = se3.yaw_to_matrix(boxes[..., 6])  # B×K×3×3
    return local @ R.transpose(-1, -2) + boxes[..., None, :3]  # B×K×8×3


def transform_boxes(a_T_b: torch.Tensor, boxes_b: torch.Tensor, *, tol: float = 1e-4) -> torch.Tensor:
    """Re-express boxes given in frame b in frame a: centre ← a_T_b · centre, yaw ← yaw + yaw(a_T_b).

    a_T_b: B×4×4 (its rotation must be about Y), boxes_b: B×K×7 -> boxes_a: B×K×7 with yaw in (−π, π].
    Raises NotYawRotationError if the rotation has a pitch/roll component beyond `tol`.
    """
    _check_boxes("boxes_b", boxes_b)
    R, t = se3.split_rt(a_T_b)
    off_axis = torch.stack([R[..., 0, 1], R[..., 1, 0], R[..., 1, 2], R[..., 2, 1], R[..., 1, 1] - 1.0], -1)
    if bool((off_axis.abs() > tol).any()):
        raise NotYawRotationError(f"a_T_b: rotation is not about Y (largest off-axis term "
                                  f"{off_axis.abs().max().item():.3g} > tol {tol}); boxes only carry a yaw")
    centre = se3.apply(a_T_b, boxes_b[..., :3])  # B×K×3
    yaw = se3.wrap_angle(boxes_b[..., 6] + se3.matrix_to_yaw(R).unsqueeze(-1))  # B×K
    return torch.cat([centre, boxes_b[..., 3:6], yaw.unsqueeze(-1)], dim=-1)


@full_precision
def points_in_boxes(xyz: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Which points lie inside (or on the surface of) which box; points and boxes in the same frame.

    xyz: B×N×3, boxes: B×K×7 -> B×N×K bool. Zero-padded rows (all lengths 0) contain no point
    other than one exactly at their centre: mask them with the validity flags.
    """
    _check_boxes("boxes", boxes)
    if xyz.dim() != 3 or xyz.shape[-1] != 3 or xyz.shape[0] != boxes.shape[0]:
        raise ShapeError(f"xyz: expected B×N×3 with B={boxes.shape[0]}, got {'×'.join(map(str, xyz.shape))}")
    R = se3.yaw_to_matrix(boxes[..., 6])  # B×K×3×3
    rel = xyz[:, :, None, :] - boxes[:, None, :, :3]  # B×N×K×3
    local = (rel.unsqueeze(-2) @ R.unsqueeze(1)).squeeze(-2)  # B×N×K×3, = R^T (p − c)
    return (local.abs() <= 0.5 * boxes[:, None, :, 3:6]).all(-1)


def boxes_to_kitti(boxes_cam: torch.Tensor) -> torch.Tensor:
    """Canonical boxes (frame cam) -> KITTI rows (h, w, l, x, y_bottom, z, ry). B×K×7 -> B×K×7."""
    _check_boxes("boxes_cam", boxes_cam)
    x, y, z, lx, ly, lz, yaw = boxes_cam.unbind(-1)
    return torch.stack([ly, lz, lx, x, y + 0.5 * ly, z, yaw], dim=-1)


def kitti_to_boxes(kitti: torch.Tensor) -> torch.Tensor:
    """KITTI rows (h, w, l, x, y_bottom, z, ry) in cam -> canonical boxes in cam. B×K×7 -> B×K×7."""
    _check_boxes("kitti", kitti)
    h, w, l, x, y, z, ry = kitti.unbind(-1)
    return torch.stack([x, y - 0.5 * h, z, l, h, w, ry], dim=-1)
