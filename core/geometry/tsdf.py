"""Projective truncated signed distance (TSDF) of depth images on a grid, and cell-mean point clouds.

Conventions (docs/conventions.md): volumes B×C×Z×Y×X on a GridConfig in `ref` metres; pixel (u, v) has its
centre at integer coordinates (column u, row v), as core.geometry.camera's `project` gives them; depth is
metres along the camera's Z, 0 where a pixel has none.

Projective TSDF (KinectFusion's): for a voxel centre x and a view, sdf = depth(π(x)) − z_cam(x), positive in
front of the surface, clipped to [−trunc, trunc] and divided by trunc; behind the surface by more than trunc
the view says nothing (occluded). Views are averaged where they say something; `known` marks voxels with at
least one view's value. Why bilinear depth: the zero crossing of a plane seen at a grazing angle then lies on
the plane; a nearest-pixel lookup puts a staircase there, whose alignment optimum lies off the true pose
(measured on 8 of the small report's moving-camera test pairs, a scratch version of the alignment started
from the truth: 0.00066 rad / 0.011 m off with nearest pixels at 0.125 m voxels, 0.00013 / 0.0027 with
bilinear depth; docs/findings.md, "Egomotion"). Where the four pixels around the projection disagree by more
than `max_spread` of their largest depth (a depth edge) the view says nothing, instead of interpolating across
the edge.

Only voxels within `band_voxels` of one of the frame's own depth points are evaluated (the rest stay unknown):
alignment reads the TSDF only near surfaces, and the band is a sixth of the grid (small preset, factor 4).
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.camera import depth_to_points, project
from core.geometry.grid import GridConfig
from core.geometry.voxelize import voxelize
from core.precision import full_precision


def bilinear_depth(depth: torch.Tensor, uv: torch.Tensor, *, max_spread: float = 0.05) -> torch.Tensor:
    """depth B×H×W, uv B×N×2 pixel coordinates -> B×N bilinear depth; 0 outside the image, where a neighbour
    has no depth, or where the four neighbours' spread exceeds `max_spread` × their largest depth."""
    B, H, W = depth.shape
    check_shape("uv", uv, (B, None, 2))
    u0, v0 = uv[..., 0].floor(), uv[..., 1].floor()  # B×N
    inside = (u0 >= 0) & (u0 < W - 1) & (v0 >= 0) & (v0 < H - 1)
    fu, fv = uv[..., 0] - u0, uv[..., 1] - v0
    iu = torch.where(inside, u0, torch.zeros_like(u0)).long()
    iv = torch.where(inside, v0, torch.zeros_like(v0)).long()
    flat = depth.reshape(B, H * W)
    corners = torch.stack([flat.gather(1, iv * W + iu), flat.gather(1, iv * W + iu + 1),
                           flat.gather(1, (iv + 1) * W + iu), flat.gather(1, (iv + 1) * W + iu + 1)])  # 4×B×N
    lo, hi = corners.min(0).values, corners.max(0).values
    ok = inside & (lo > 0) & (hi - lo <= max_spread * hi)
    value = (corners[0] * (1 - fu) + corners[1] * fu) * (1 - fv) + (corners[2] * (1 - fu) + corners[3] * fu) * fv
    return torch.where(ok, value, torch.zeros_like(value))


def views_points_in_ref(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """Every view's depth points in `ref`: depth B×V×H×W, pix_T_cam / cam_T_ref B×V×4×4 -> (xyz B×(V·H·W)×3,
    valid B×(V·H·W))."""
    B, V, H, W = depth.shape
    xyz_cam, valid = depth_to_points(depth.reshape(B * V, H, W), pix_T_cam.reshape(B * V, 4, 4))  # BV×HW×3, BV×HW
    xyz_ref = se3.apply(se3.invert(cam_T_ref.reshape(B * V, 4, 4)), xyz_cam)  # BV×HW×3
    return xyz_ref.reshape(B, V * H * W, 3), valid.reshape(B, V * H * W)


def surface_band(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor, grid: GridConfig,
                 band_voxels: int) -> torch.Tensor:
    """Voxels within `band_voxels` (Chebyshev) of a depth point of any view: depth B×V×H×W, pix_T_cam /
    cam_T_ref B×V×4×4 -> B×Z×Y×X bool."""
    xyz_ref, valid = views_points_in_ref(depth, pix_T_cam, cam_T_ref)  # B×N×3, B×N
    occupied = voxelize(xyz_ref, grid, valid)  # B×1×Z×Y×X
    # Dilation by a (2b+1)³ cube as three 1D box sums (a cube is separable), each a difference of cumulative
    # sums: O(1) per voxel and axis (pooling ops took ~0.5 s on a small grid at factor 4, one thread).
    for dim in (2, 3, 4):
        occupied = _box_sum(occupied, band_voxels, dim)
    return occupied[:, 0] > 0.5  # B×Z×Y×X (sums of ones: ≥ 1 where any point is near)


def _box_sum(vol: torch.Tensor, radius: int, dim: int) -> torch.Tensor:
    """Sum of `vol` over a window of ±radius along `dim` (zero outside), same shape."""
    n = vol.shape[dim]
    c = vol.cumsum(dim)  # C[k] = Σ_{j ≤ k}
    zeros = torch.zeros_like(c.narrow(dim, 0, 1)).expand(*[radius + 1 if d == dim else -1 for d in range(vol.dim())])
    last = c.narrow(dim, n - 1, 1).expand(*[radius if d == dim else -1 for d in range(vol.dim())])
    c = torch.cat([zeros, c, last], dim)  # P[m] = C[m − r − 1], 0 before the start, C[n − 1] past the end
    return c.narrow(dim, 2 * radius + 1, n) - c.narrow(dim, 0, n)  # C[i + r] − C[i − r − 1]


@full_precision  # depths, projections and distances in float32 at least under bf16 autocast
def projective_tsdf(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor, grid: GridConfig, *,
                    truncation_m: float, band_voxels: int, max_spread: float = 0.05) -> torch.Tensor:
    """The views' fused projective TSDF on `grid` (module docstring).

    depth: B×V×H×W; pix_T_cam, cam_T_ref: B×V×4×4 -> B×2×Z×Y×X: channel 0 the TSDF in [−1, 1] (0 where
    unknown), channel 1 `known` in {0, 1}.
    """
    B, V, H, W = depth.shape
    check_shape("pix_T_cam", pix_T_cam, (B, V, 4, 4))
    check_shape("cam_T_ref", cam_T_ref, (B, V, 4, 4))
    if truncation_m <= 0:
        raise ValueError(f"projective_tsdf: truncation_m must be positive, got {truncation_m}")
    band = surface_band(depth, pix_T_cam, cam_T_ref, grid, band_voxels).reshape(B, -1)  # B×(Z·Y·X)
    lo = torch.tensor(grid.bounds_min, dtype=depth.dtype, device=depth.device)
    out = depth.new_zeros(B, 2, grid.Z * grid.Y * grid.X)
    for b in range(B):
        index = band[b].nonzero()[:, 0]  # M, flat z·Y·X + y·X + x
        ijk = torch.stack([index % grid.X, index // grid.X % grid.Y, index // (grid.X * grid.Y)], -1)  # M×3 (x, y, z)
        x_ref = ((ijk.to(depth.dtype) + 0.5) * grid.voxel_size + lo).expand(V, -1, 3)  # V×M×3 voxel centres
        uv, z = project(pix_T_cam[b], se3.apply(cam_T_ref[b], x_ref))  # V×M×2, V×M (every view at once)
        d = bilinear_depth(depth[b], uv, max_spread=max_spread)  # V×M
        sdf = d - z
        says = (z > 0) & (d > 0) & (sdf > -truncation_m)  # V×M
        total = torch.where(says, (sdf / truncation_m).clamp(-1.0, 1.0), torch.zeros_like(sdf)).sum(0)  # M
        count = says.sum(0).to(depth.dtype)  # M
        out[b, 0, index] = total / count.clamp_min(1.0)  # 0 where no view says anything
        out[b, 1, index] = (count > 0).to(out.dtype)
    return out.reshape(B, 2, grid.Z, grid.Y, grid.X)  # B×2×Z×Y×X


def cell_mean_points(xyz: torch.Tensor, valid: torch.Tensor, grid: GridConfig, cell_m: float
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """One point per occupied cube of edge `cell_m` inside `grid` (the mean of its points; cubes aligned to
    the grid's minimum corner), as core.baselines.icp.voxel_downsample does for one cloud.

    xyz: B×N×3, valid: B×N -> (points B×M×3, points_valid B×M), M the largest count over the batch (padding
    rows are zeros, not valid)."""
    B, N, _ = xyz.shape
    check_shape("valid", valid, (B, N))
    lo = torch.tensor(grid.bounds_min, dtype=xyz.dtype, device=xyz.device)
    hi = torch.tensor(grid.bounds_max, dtype=xyz.dtype, device=xyz.device)
    clouds = []
    for b in range(B):
        keep = valid[b] & ((xyz[b] >= lo) & (xyz[b] < hi)).all(-1)
        p = xyz[b][keep]  # n×3
        ijk = torch.floor((p - lo) / cell_m).long()  # n×3, each in [0, cells along that axis)
        cells = torch.ceil((hi - lo) / cell_m).long() + 1  # 3 (x, y, z)
        keys = (ijk[:, 2] * cells[1] + ijk[:, 1]) * cells[0] + ijk[:, 0]  # n, one int per cube
        # (torch.unique over rows, dim=0, compares row by row in Python-level loops: 0.6 s for one tiny frame)
        _, inverse = torch.unique(keys, return_inverse=True)
        sums = p.new_zeros(int(inverse.max()) + 1 if len(p) else 0, 3).index_add_(0, inverse, p)
        counts = p.new_zeros(len(sums)).index_add_(0, inverse, torch.ones_like(p[:, 0]))
        clouds.append(sums / counts[:, None].clamp_min(1.0))
    M = max(1, max(len(c) for c in clouds))
    points, points_valid = xyz.new_zeros(B, M, 3), torch.zeros(B, M, dtype=torch.bool, device=xyz.device)
    for b, c in enumerate(clouds):
        points[b, :len(c)], points_valid[b, :len(c)] = c, True
    return points, points_valid
