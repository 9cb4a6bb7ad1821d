"""The egomotion module's last stage at inference: dense alignment on a grid finer than the map's.

Conventions (docs/conventions.md#poses): E = `ref0_T_ref1` (B×4×4); fine volumes B×1×(f·Z)×(f·Y)×(f·X) on
`fine_grid(grid, f)` (the map grid's bounds, f times its resolution), each frame in its own ref_t.

Why: the sub-voxel stage (core.models.egomotion_refine) aligns the points' splatted occupancy on the map
grid, and its optimum lies where the 0.5 m splat puts it, not at the truth. Measured (session 15, small,
32 held-out moving-camera pairs of `data generate --seed 7 --moving-ego on`; out of the README's
"Egomotion" bullet): Gauss-Newton on fixed splats of the TRUE frames, started from the truth, ends at
R 0.00177 rad / t 0.040 m at 0.5 m voxels — 1.29 × point-to-plane ICP's rotation error (0.00137 rad /
0.038 m) — and at 0.00074 rad / 0.015 m at 0.25 m voxels. The finer grid's basin is too narrow to start
from the identity (0.0030 rad / 0.14 m), but started where the map grid's alignment ends it reaches
0.00073 rad / 0.015 m. So this stage starts from the module's refined estimate and runs plain geometric
Gauss-Newton (no learned part, so training never runs it: the module trains as before) on the max over
the views of each view's surface splat (core.geometry.splat.surface_splat, clamped to 1: the same
occupancy as the module's "splat" input volumes) at `factor` times the resolution.

Iterations: 3 (on 48 held-out pairs of seed 8: mean / median rotation error 0.00066 / 0.00041 rad with 3,
0.00068 / 0.00039 with 6, 0.00065 / 0.00045 with 2; 3 instead of 6 saves ~37 ms per pair at small).

Cost: a fine volume is factor³ the map grid's voxels (small, factor 2: 128×32×128 = 524 288 floats per
frame); Gauss-Newton samples only the voxels with a non-zero gradient.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch

from core.errors import check_shape
from core.geometry.camera import depth_to_points
from core.geometry.grid import GridConfig
from core.geometry.splat import surface_splat
from core.models.egomotion_refine import gauss_newton_refine, gaussian_blur3d


@dataclass(frozen=True, kw_only=True)
class FineAlignment:
    """factor: the fine grid's resolution over the map grid's; levels: (blur σ in fine voxels, Cauchy robust
    scale, Gauss-Newton iterations) as core.models.egomotion_refine.DEFAULT_LEVELS, run in order."""

    factor: int = 2
    levels: tuple[tuple[float, float, int], ...] = ((0.7, 0.1, 3),)
    damping: float = 1e-3
    max_step: tuple[float, float] = (0.05, 1.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "levels", tuple((float(s), float(r), int(n)) for s, r, n in self.levels))
        object.__setattr__(self, "max_step", (float(self.max_step[0]), float(self.max_step[1])))
        if self.factor < 1:
            raise ValueError(f"FineAlignment: factor must be >= 1, got {self.factor}")
        if not self.levels or min(n for _, _, n in self.levels) < 1:
            raise ValueError(f"FineAlignment: levels need >= 1 iteration each, got {self.levels}")

    def to_dict(self) -> dict:
        return {"factor": self.factor, "levels": [list(l) for l in self.levels], "damping": self.damping,
                "max_step": list(self.max_step)}


def fine_grid(grid: GridConfig, factor: int) -> GridConfig:
    """The grid with `grid`'s bounds and `factor` times its voxels along every axis."""
    return replace(grid, Z=grid.Z * factor, Y=grid.Y * factor, X=grid.X * factor)


def fine_occupancy(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                   grid: GridConfig) -> torch.Tensor:
    """depth B×V×H×W, pix_T_cam / cam_T_ref B×V×4×4 -> the max over views of each view's surface splat on
    `grid`, clamped to 1: B×1×Z×Y×X."""
    B, V, H, W = depth.shape
    check_shape("pix_T_cam", pix_T_cam, (B, V, 4, 4))
    check_shape("cam_T_ref", cam_T_ref, (B, V, 4, 4))
    xyz_cam, valid = depth_to_points(depth.reshape(B * V, H, W), pix_T_cam.reshape(B * V, 4, 4))  # BV×N×3, BV×N
    splat = surface_splat(xyz_cam, valid, pix_T_cam.reshape(B * V, 4, 4), cam_T_ref.reshape(B * V, 4, 4), grid)
    splat = splat.reshape(B, V, 1, *grid.shape_zyx)  # B×V×1×Z×Y×X
    return splat.amax(dim=1).clamp(max=1.0)  # B×1×Z×Y×X


def align_fine(estimate: torch.Tensor, reference: torch.Tensor, query: torch.Tensor, grid: GridConfig,
               config: FineAlignment) -> torch.Tensor:
    """estimate B×4×4 (ref0_T_ref1), reference (ref0) / query (ref1) fine volumes B×1×Z×Y×X on `grid` ->
    the estimate after the config's Gauss-Newton levels: B×4×4."""
    check_shape("reference", reference, (estimate.shape[0], 1, *grid.shape_zyx))
    check_shape("query", query, tuple(reference.shape))
    E = estimate
    for sigma, robust, iterations in config.levels:
        E, _ = gauss_newton_refine(gaussian_blur3d(reference, sigma), gaussian_blur3d(query, sigma), E, grid,
                                   iterations=iterations, damping=config.damping, robust_scale=robust,
                                   max_step=config.max_step)
    return E
