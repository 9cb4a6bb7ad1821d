"""Trilinear resampling of voxel volumes: at points, under a rigid motion, along a flow field.

Conventions (docs/conventions.md#the-map-grid):
- Volumes are B×C×Z×Y×X; point sets B×N×3 in (x, y, z) order; flow volumes B×3×Z×Y×X with channels
  (x, y, z) in voxel units.
- `mem` holds voxel index coordinates: integer values are voxel CENTRES, mem = (ref − min)/voxel − 0.5.
- Poses are 4×4 `a_T_b` with p_a = a_T_b @ p_b; `ref` is the map frame (OpenCV-like: X right, Y down,
  Z forward, metres).

Every sampler here uses `grid_sample(..., align_corners=True)` with x_norm = 2·x_mem/(X−1) − 1, so
mem coordinate 0 hits the centre of the first voxel and X−1 the centre of the last: identity warps are
exact and a translation of k voxels shifts the volume by exactly k. Outside the volume the samplers see
zeros: values fade linearly to 0 over the one voxel beyond the outermost centres, and are 0 further out.
A dimension of size 1 is zero-padded to size 3 before sampling (align_corners=True would otherwise map
every coordinate onto its single voxel), which keeps those zero-outside semantics.
Outputs are differentiable w.r.t. the volume and the sampling coordinates (so also the pose / flow).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from core.errors import ShapeError, check_shape
from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref, ref_T_mem, voxel_centers_mem
from core.precision import full_precision


def _check_volume(name: str, vol: torch.Tensor) -> None:
    if not isinstance(vol, torch.Tensor) or vol.dim() != 5:
        shape = "×".join(map(str, getattr(vol, "shape", ()))) or type(vol).__name__
        raise ShapeError(f"{name}: expected a volume B×C×Z×Y×X, got {shape}")


def check_volume_matches_grid(name: str, vol: torch.Tensor, grid: GridConfig) -> None:
    """Raise ShapeError unless vol is B×C×Z×Y×X with (Z, Y, X) = grid's counts."""
    _check_volume(name, vol)
    if tuple(vol.shape[-3:]) != grid.shape_zyx:
        raise ShapeError(f"{name}: volume is {'×'.join(map(str, vol.shape))} but the grid is "
                         f"Z×Y×X = {'×'.join(map(str, grid.shape_zyx))} (for a coarser volume pass grid.scaled(...))")


@full_precision  # under autocast: float32 volume and coordinates, not the bf16 volume's dtype
def sample_volume_at(vol: torch.Tensor, xyz_mem: torch.Tensor) -> torch.Tensor:
    """Trilinear samples of `vol` at mem coordinates arranged in any B×…×3 layout.

    vol: B×C×Z×Y×X, xyz_mem: B×D1×D2×D3×3 (exactly three middle dims) -> B×C×D1×D2×D3. Zeros outside.
    """
    _check_volume("vol", vol)
    if xyz_mem.dim() != 5 or xyz_mem.shape[-1] != 3 or xyz_mem.shape[0] != vol.shape[0]:
        raise ShapeError(f"xyz_mem: expected B×D1×D2×D3×3 with B={vol.shape[0]}, got "
                         f"{'×'.join(map(str, xyz_mem.shape))}")
    xyz = xyz_mem.to(vol.dtype)
    sizes = list(vol.shape[-3:])  # Z, Y, X
    if 1 in sizes:
        # Pad each size-1 axis with a zero voxel on both sides and shift coordinates by one (see module doc).
        pad = []
        for axis_size in reversed(sizes):  # F.pad order: X, Y, Z
            pad += [1, 1] if axis_size == 1 else [0, 0]
        vol = F.pad(vol, pad)
        shift = torch.tensor([1.0 if sizes[2] == 1 else 0.0, 1.0 if sizes[1] == 1 else 0.0,
                              1.0 if sizes[0] == 1 else 0.0], dtype=xyz.dtype, device=xyz.device)
        xyz = xyz + shift
        sizes = list(vol.shape[-3:])
    size_xyz = torch.tensor([sizes[2], sizes[1], sizes[0]], dtype=xyz.dtype, device=xyz.device)
    norm = 2.0 * xyz / (size_xyz - 1.0) - 1.0  # B×D1×D2×D3×3, (x, y, z) as grid_sample wants
    return F.grid_sample(vol, norm, mode="bilinear", padding_mode="zeros", align_corners=True)


def sample_volume(vol: torch.Tensor, xyz_mem: torch.Tensor) -> torch.Tensor:
    """Trilinear samples of `vol` at points given in mem coordinates (zeros outside).

    vol: B×C×Z×Y×X, xyz_mem: B×N×3 (x, y, z) -> B×C×N.
    """
    check_shape("xyz_mem", xyz_mem, (vol.shape[0] if isinstance(vol, torch.Tensor) else None, None, 3))
    B, N = xyz_mem.shape[:2]
    out = sample_volume_at(vol, xyz_mem.reshape(B, 1, 1, N, 3))  # B×C×1×1×N
    return out.reshape(B, vol.shape[1], N)  # B×C×N


def warp_rigid(vol_b: torch.Tensor, b_T_a: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """Resample a volume living in frame b into frame a (both on the same grid layout).

    vol_b: B×C×Z×Y×X, b_T_a: B×4×4 (ref_b ← ref_a), grid with (Z, Y, X) = vol_b's -> vol_a: B×C×Z×Y×X,
    where vol_a(p) = vol_b(mem(b_T_a · ref(p))) for each voxel centre p of frame a.
    """
    check_volume_matches_grid("vol_b", vol_b, grid)
    check_shape("b_T_a", b_T_a, (vol_b.shape[0], 4, 4))
    xyz_b = rigid_sample_points(b_T_a, grid, dtype=vol_b.dtype).reshape(-1, grid.Z, grid.Y, grid.X, 3)  # B×Z×Y×X×3
    return sample_volume_at(vol_b, xyz_b)


def rigid_sample_points(b_T_a: torch.Tensor, grid: GridConfig, *, dtype: torch.dtype) -> torch.Tensor:
    """Where each voxel centre of frame a lands in frame b's mem coordinates: b_T_a B×4×4 -> B×(Z·Y·X)×3
    (x, y, z), voxels in Z, Y, X order (what `warp_rigid` samples)."""
    B, device = b_T_a.shape[0], b_T_a.device
    memb_T_mema = se3.compose(se3.compose(mem_T_ref(grid, dtype=dtype, device=device).expand(B, 4, 4),
                                          b_T_a.to(dtype)),
                              ref_T_mem(grid, dtype=dtype, device=device).expand(B, 4, 4))  # B×4×4
    centres = voxel_centers_mem(grid, dtype=dtype, device=device).expand(B, -1, 3)  # B×ZYX×3
    return se3.apply(memb_T_mema, centres)  # B×ZYX×3


def warp_flow(vol: torch.Tensor, flow: torch.Tensor) -> torch.Tensor:
    """Backward warp by a flow field in voxels: vol'(p) = vol(p + flow(p)) (trilinear, zeros outside).

    vol: B×C×Z×Y×X, flow: B×3×Z×Y×X (channels x, y, z; voxel units) -> B×C×Z×Y×X.
    """
    _check_volume("vol", vol)
    check_shape("flow", flow, (vol.shape[0], 3, *vol.shape[-3:]))
    B, _, Z, Y, X = vol.shape
    dtype, device = vol.dtype, vol.device
    z, y, x = torch.meshgrid(torch.arange(Z, dtype=dtype, device=device), torch.arange(Y, dtype=dtype, device=device),
                             torch.arange(X, dtype=dtype, device=device), indexing="ij")
    base = torch.stack([x, y, z], dim=-1)  # Z×Y×X×3
    target = base + flow.to(dtype).permute(0, 2, 3, 4, 1)  # B×Z×Y×X×3
    return sample_volume_at(vol, target)
