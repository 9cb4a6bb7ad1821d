"""Rigid transforms (SE(3)) and rotation parameterisations, batched torch.

Conventions (docs/conventions.md#poses):
- Frames: `pix` (u right, v down, integer coordinates are pixel centres), `cam` (OpenCV: X right,
  Y down, Z forward, metres), `ref` (the map's frame), `mem` (voxel index coordinates, integer = voxel
  centre), `world`.
- A pose is a 4×4 homogeneous matrix named `a_T_b` with `p_a = a_T_b @ p_b`; composition reads
  left to right: `a_T_c = a_T_b @ b_T_c`.
- Point sets are B×N×3 in (x, y, z) order. Angles are radians.
- Quaternions are (w, x, y, z) (scalar first), unit norm; `matrix_to_quaternion` returns w >= 0.
- Euler angles: R = Rz(rz) · Ry(ry) · Rx(rx), each about the frame's own X, Y, Z axis.
- Yaw is a rotation about Y (down): R = [[c, 0, s], [0, 1, 0], [-s, 0, c]] (the same as KITTI's `ry`).

Every function accepts any number of leading batch dimensions (written `...` below; usually `B`);
device and dtype follow the inputs. All functions are differentiable (autograd) except `is_rigid`.
The ones that multiply matrices run in float32 under torch.autocast (core.precision.full_precision):
autocast would otherwise compute poses and points in bf16.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from core.errors import ShapeError
from core.precision import full_precision


def _check_last(name: str, t: torch.Tensor, trailing: tuple[int, ...]) -> None:
    if not isinstance(t, torch.Tensor):
        raise ShapeError(f"{name}: expected a torch.Tensor, got {type(t).__name__}")
    if tuple(t.shape[-len(trailing):]) != trailing or t.dim() < len(trailing):
        want = "…×" + "×".join(map(str, trailing))
        raise ShapeError(f"{name}: expected shape {want}, got {'×'.join(map(str, t.shape)) or 'scalar'}")


# ----------------------------------------------------------------------------- 4×4 transforms

@full_precision
def compose(a_T_b: torch.Tensor, b_T_c: torch.Tensor) -> torch.Tensor:
    """a_T_c = a_T_b @ b_T_c. Shapes ...×4×4 (leading dims broadcast)."""
    _check_last("a_T_b", a_T_b, (4, 4))
    _check_last("b_T_c", b_T_c, (4, 4))
    return a_T_b @ b_T_c


def split_rt(a_T_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """...×4×4 -> (R: ...×3×3, t: ...×3)."""
    _check_last("a_T_b", a_T_b, (4, 4))
    return a_T_b[..., :3, :3], a_T_b[..., :3, 3]


def from_rt(R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(R: ...×3×3, t: ...×3) -> ...×4×4 with bottom row (0, 0, 0, 1)."""
    _check_last("R", R, (3, 3))
    _check_last("t", t, (3,))
    # numpy's broadcast_shapes: torch.broadcast_shapes imports torch's meta registrations (~3 s, once).
    batch = np.broadcast_shapes(tuple(R.shape[:-2]), tuple(t.shape[:-1]))
    R, t = R.expand(*batch, 3, 3), t.expand(*batch, 3)
    top = torch.cat([R, t.unsqueeze(-1)], dim=-1)  # ...×3×4
    bottom = torch.zeros(*top.shape[:-2], 1, 4, dtype=top.dtype, device=top.device)
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)  # ...×4×4


@full_precision
def invert(a_T_b: torch.Tensor) -> torch.Tensor:
    """b_T_a for a rigid a_T_b (uses R^T, not a general inverse). ...×4×4 -> ...×4×4."""
    R, t = split_rt(a_T_b)
    Rt = R.transpose(-1, -2)  # ...×3×3
    return from_rt(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))


@full_precision
def apply(a_T_b: torch.Tensor, xyz_b: torch.Tensor) -> torch.Tensor:
    """Transform points: xyz_a = a_T_b · xyz_b. a_T_b: B×4×4 (or ...×4×4), xyz_b: B×N×3 -> B×N×3.

    Works for any affine 4×4 (e.g. `mem_T_ref` similarities), not only rigid ones.
    """
    _check_last("a_T_b", a_T_b, (4, 4))
    _check_last("xyz_b", xyz_b, (3,))
    R = a_T_b[..., :3, :3]  # ...×3×3
    t = a_T_b[..., :3, 3]  # ...×3
    return xyz_b @ R.transpose(-1, -2) + t.unsqueeze(-2)  # B×N×3


@full_precision
def is_rigid(a_T_b: torch.Tensor, tol: float = 1e-4) -> torch.Tensor:
    """...×4×4 -> ... bool: finite, bottom row (0,0,0,1), R^T R = I and det R = +1 within `tol`."""
    _check_last("a_T_b", a_T_b, (4, 4))
    T = a_T_b.detach()
    finite = torch.isfinite(T).flatten(-2).all(-1)
    bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=T.dtype, device=T.device)
    bottom_ok = (T[..., 3, :] - bottom).abs().amax(-1) <= tol
    R = torch.nan_to_num(T[..., :3, :3])
    eye = torch.eye(3, dtype=T.dtype, device=T.device)
    ortho_ok = (R.transpose(-1, -2) @ R - eye).abs().flatten(-2).amax(-1) <= tol
    det_ok = (torch.linalg.det(R) - 1.0).abs() <= tol
    return finite & bottom_ok & ortho_ok & det_ok


def random_rigid(B: int, max_angle_rad: float, max_translation_m: float,
                 generator: torch.Generator | None = None, *, dtype: torch.dtype = torch.float32,
                 device: torch.device | str | None = None) -> torch.Tensor:
    """B random rigid transforms B×4×4: axis uniform on the sphere, angle uniform in
    [-max_angle_rad, max_angle_rad], translation uniform per axis in [-max_translation_m, max_translation_m].

    Random numbers are drawn on the generator's device (CPU when `generator` is None and `device` is
    None) in float64, so a seed gives the same transforms on every device; the result is moved to `device`.
    """
    draw_device = generator.device if generator is not None else (device or "cpu")
    opts = dict(dtype=torch.float64, device=draw_device, generator=generator)
    axis = torch.randn(B, 3, **opts)
    axis = axis / axis.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    angle = (torch.rand(B, 1, **opts) * 2.0 - 1.0) * max_angle_rad
    trans = (torch.rand(B, 3, **opts) * 2.0 - 1.0) * max_translation_m
    T = from_rt(axis_angle_to_matrix(axis * angle), trans)
    return T.to(dtype=dtype, device=device if device is not None else draw_device)


# ----------------------------------------------------------------------------- rotations

def _skew(v: torch.Tensor) -> torch.Tensor:
    """...×3 -> ...×3×3 cross-product matrix [v]_x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).unflatten(-1, (3, 3))  # ...×3×3


@full_precision
def axis_angle_to_matrix(axis_angle: torch.Tensor) -> torch.Tensor:
    """Rodrigues: ...×3 (axis × angle, radians) -> ...×3×3. Stable and differentiable at angle 0."""
    _check_last("axis_angle", axis_angle, (3,))
    theta2 = (axis_angle * axis_angle).sum(-1, keepdim=True).unsqueeze(-1)  # ...×1×1
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    # sin(θ)/θ and (1-cos θ)/θ² with Taylor series near 0, where the closed forms lose precision.
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    K = _skew(axis_angle)
    eye = torch.eye(3, dtype=axis_angle.dtype, device=axis_angle.device)
    return eye + a * K + b * (K @ K)


def quaternion_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """...×4 quaternion (w, x, y, z) -> ...×3×3. The input is normalised first."""
    _check_last("q", q, (4,))
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).unflatten(-1, (3, 3))  # ...×3×3


def matrix_to_quaternion(R: torch.Tensor) -> torch.Tensor:
    """...×3×3 rotation -> ...×4 unit quaternion (w, x, y, z) with w >= 0.

    Builds the four candidate quaternions (one per largest diagonal term, as in Shepperd's method) and
    keeps, per matrix, the best-conditioned one, so it is accurate near 180° as well.
    """
    _check_last("R", R, (3, 3))
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    # 4·q_i² for i = w, x, y, z
    q_abs = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22,
                         1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1).clamp_min(0).sqrt()  # ...×4
    candidates = torch.stack([
        torch.stack([q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01], dim=-1),
        torch.stack([m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20], dim=-1),
        torch.stack([m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21], dim=-1),
        torch.stack([m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2], dim=-1),
    ], dim=-2)  # ...×4×4 (row i = candidate computed from q_i)
    candidates = candidates / (2.0 * q_abs.clamp_min(0.1)).unsqueeze(-1)
    best = q_abs.argmax(dim=-1)  # ...
    q = torch.gather(candidates, -2, best[..., None, None].expand(*best.shape, 1, 4)).squeeze(-2)  # ...×4
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return torch.where(q[..., :1] < 0, -q, q)


def quaternion_to_axis_angle(q: torch.Tensor) -> torch.Tensor:
    """...×4 (w, x, y, z) -> ...×3 axis × angle with angle in [0, π]."""
    _check_last("q", q, (4,))
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q = torch.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    # angle / sin(angle/2) = angle / s, with its limit 2 (+ s²/3) at s -> 0.
    small = s < 1e-6
    scale = torch.where(small, 2.0 + s * s / 3.0, angle / s.clamp_min(1e-12))
    return v * scale


def matrix_to_axis_angle(R: torch.Tensor) -> torch.Tensor:
    """...×3×3 -> ...×3 axis × angle (angle in [0, π]); via the quaternion, so stable near 0 and π."""
    return quaternion_to_axis_angle(matrix_to_quaternion(R))


def euler_to_matrix(rx: torch.Tensor, ry: torch.Tensor, rz: torch.Tensor) -> torch.Tensor:
    """Angles ... (radians, about the frame's X, Y, Z) -> ...×3×3 with R = Rz(rz) · Ry(ry) · Rx(rx)."""
    rx, ry, rz = torch.broadcast_tensors(torch.as_tensor(rx), torch.as_tensor(ry), torch.as_tensor(rz))
    cx, sx, cy, sy, cz, sz = rx.cos(), rx.sin(), ry.cos(), ry.sin(), rz.cos(), rz.sin()
    return torch.stack([
        cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx,
        sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx,
        -sy, cy * sx, cy * cx,
    ], dim=-1).unflatten(-1, (3, 3))  # ...×3×3


def matrix_to_euler(R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """...×3×3 -> (rx, ry, rz), each ..., inverse of `euler_to_matrix` with ry in [-π/2, π/2].

    At gimbal lock (|ry| = π/2) the split between rx and rz is arbitrary; the returned triple still
    rebuilds R up to rounding.
    """
    _check_last("R", R, (3, 3))
    ry = torch.asin((-R[..., 2, 0]).clamp(-1.0, 1.0))
    cy = torch.sqrt(R[..., 2, 1] ** 2 + R[..., 2, 2] ** 2)
    locked = cy < 1e-6
    rx = torch.where(locked, torch.zeros_like(ry), torch.atan2(R[..., 2, 1], R[..., 2, 2]))
    # At gimbal lock set rx = 0; then R[0,1] = -sin(rz), R[1,1] = cos(rz).
    rz = torch.where(locked, torch.atan2(-R[..., 0, 1], R[..., 1, 1]), torch.atan2(R[..., 1, 0], R[..., 0, 0]))
    return rx, ry, rz


def yaw_to_matrix(yaw: torch.Tensor) -> torch.Tensor:
    """... yaw (radians about Y, down) -> ...×3×3 [[c, 0, s], [0, 1, 0], [-s, 0, c]]."""
    yaw = torch.as_tensor(yaw)
    c, s = yaw.cos(), yaw.sin()
    o, one = torch.zeros_like(c), torch.ones_like(c)
    return torch.stack([c, o, s, o, one, o, -s, o, c], dim=-1).unflatten(-1, (3, 3))  # ...×3×3


def matrix_to_yaw(R: torch.Tensor) -> torch.Tensor:
    """...×3×3 rotation about Y -> ... yaw in (-π, π] (reads R[0,2] = sin, R[0,0] = cos)."""
    _check_last("R", R, (3, 3))
    return torch.atan2(R[..., 0, 2], R[..., 0, 0])


def rotation_angle(R: torch.Tensor) -> torch.Tensor:
    """...×3×3 -> ... rotation angle in [0, π] radians (atan2 form: accurate at 0 and π)."""
    _check_last("R", R, (3, 3))
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1.0) * 0.5
    vee = torch.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    sin = 0.5 * vee.norm(dim=-1)
    return torch.atan2(sin, cos)


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Wrap radians to (-π, π]."""
    return angle - 2.0 * math.pi * torch.ceil((angle - math.pi) / (2.0 * math.pi))
