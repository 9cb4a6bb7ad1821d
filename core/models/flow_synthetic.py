"""Synthetic rigid motions of a single feature volume: the supervised half of 3D flow training.

Conventions (DESIGN.md §2): poses 4×4, `ref` metres, `mem` voxel coordinates (integer = centre);
flow B×3×Z×Y×X (x, y, z) in voxels from t to t+1.

A motion M (ref_t → ref_t, applied to the scene) moves the point at ref position x to M·x. The moved
volume is vol1 = warp_rigid(vol0, inv(M), grid) (vol1(p) = vol0(M⁻¹ p)) and the flow is
flow(p) = mem(M · ref(p)) − p, so warp_flow(vol1, flow) = vol0 where both are defined.
Motions are drawn in equal thirds from the paper's three distributions: large (angles ±6°, translations
±1 m), small (±1°, ±0.1 m) and zero; per distribution, each Euler angle and each translation component is
uniform in its range.
"""

from __future__ import annotations

import math

import torch

from core.geometry import se3
from core.geometry.grid import GridConfig, mem_T_ref, ref_T_mem, voxel_centers_mem

MOTION_RANGES = {"large": (6.0, 1.0), "small": (1.0, 0.1), "zero": (0.0, 0.0)}  # (degrees, metres)


def sample_motions(B: int, *, generator: torch.Generator | None = None, dtype=torch.float32,
                   device=None) -> tuple[torch.Tensor, list[str]]:
    """B motions B×4×4 and their kinds, cycling large/small/zero from a random start (equal thirds)."""
    kinds = list(MOTION_RANGES)
    start = int(torch.randint(3, (1,), generator=generator))
    names = [kinds[(start + i) % 3] for i in range(B)]
    deg = torch.tensor([MOTION_RANGES[n][0] for n in names], dtype=torch.float64)
    met = torch.tensor([MOTION_RANGES[n][1] for n in names], dtype=torch.float64)
    u = torch.rand(B, 6, generator=generator, dtype=torch.float64) * 2.0 - 1.0  # B×6 in [-1, 1]
    angles = u[:, :3] * deg[:, None] * (math.pi / 180.0)
    R = se3.euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2])  # B×3×3
    M = se3.from_rt(R, u[:, 3:] * met[:, None])  # B×4×4
    return M.to(dtype=dtype, device=device), names


def rigid_flow(motion: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """motion B×4×4 (ref, applied to the scene) -> flow B×3×Z×Y×X in voxels of `grid`."""
    B = motion.shape[0]
    dtype, device = motion.dtype, motion.device
    memM = mem_T_ref(grid, dtype=dtype, device=device) @ motion @ ref_T_mem(grid, dtype=dtype, device=device)  # B×4×4
    p = voxel_centers_mem(grid, dtype=dtype, device=device).expand(B, -1, 3)  # B×ZYX×3
    moved = se3.apply(memM, p)  # B×ZYX×3
    flow = (moved - p).reshape(B, grid.Z, grid.Y, grid.X, 3)  # B×Z×Y×X×3
    return flow.permute(0, 4, 1, 2, 3).contiguous()  # B×3×Z×Y×X
