"""The egomotion module's last stage at inference: geometric alignment on a grid finer than the map's.

Conventions (docs/conventions.md#poses): E = `ref0_T_ref1` (B×4×4); each frame's data (`FineFrame`) lies on
`fine_grid(grid, f)` (the map grid's bounds, f times its resolution) in that frame's own ref_t.

The stage has no weights (training never runs it): it starts where the module's learned stages end and
aligns the frames' geometry. Two kinds:

- "tsdf" (the default since session 25): Gauss-Newton of frame 1's depth points against frame 0's projective
  TSDF on the fine grid (core.geometry.tsdf; KinectFusion's map, tracked as Bylow et al. 2013 track a
  frame against it): the residual of a point is the TSDF where the estimate puts it, its gradient by central
  differences of the trilinear TSDF (one-sided next to an unknown voxel), Huber weights, `iterations` steps.
  The points are frame 1's depth points reduced to one per cube of `point_cell` map voxels (as the ICP
  baseline's cloud: core.eval.protocols.egomotion). Measured on the small report's 32 moving-camera test
  pairs (docs/findings.md, "Egomotion"; tests/benchmarks/bench_egomotion_fine.py): started 0.6° / 0.25 m
  off the truth, a TSDF on 0.125 m voxels (factor 4) ends where point-to-plane ICP ends (0.99 × / 0.95 × its
  mean errors); coarser grids do not.
  A saved stage without a `kind` is a splat stage; a module saved before it had any fine stage gets this one.
- "splat" (every bundle whose saved stage has no `kind`): Gauss-Newton of the max over the views of each
  view's surface splat (core.geometry.splat.surface_splat, clamped to 1) at `factor` times the resolution,
  blur σ and Cauchy scale per level. Its optimum lies where the splats put it, not at the truth: started at
  the truth it ends 0.00089 rad / 0.016 m off at 0.25 m voxels, 0.00045 / 0.0058 at 0.125 m (a splat's mass
  follows how densely each view samples a surface, which changes with the viewpoint; a TSDF's zero crossing
  does not). Iterations: 3 (on 48 held-out pairs of seed 8: mean / median rotation error 0.00066 / 0.00041
  rad with 3, 0.00068 / 0.00039 with 6).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from core.errors import check_shape
from core.geometry import se3
from core.geometry.camera import depth_to_points
from core.geometry.grid import GridConfig, mem_T_ref
from core.geometry.resample import sample_volume_at
from core.geometry.splat import surface_splat
from core.geometry.tsdf import cell_mean_points, projective_tsdf, views_points_in_ref
from core.models.egomotion_refine import clamp_norm, gauss_newton_refine, gaussian_blur3d
from core.precision import full_precision

FINE_KINDS = ("tsdf", "splat")


@dataclass(frozen=True, kw_only=True)
class FineAlignment:
    """kind: "tsdf" or "splat" (module doc; a saved stage without a kind is a splat stage: it predates the
    TSDF); factor: the fine grid's resolution over the map grid's; damping: Levenberg-Marquardt λ relative to
    the Hessian's diagonal; max_step: (rad, m) clamp of each step.
    splat: levels (blur σ in fine voxels, Cauchy robust scale, Gauss-Newton iterations), run in order.
    tsdf: truncation (fine voxels), iterations, robust (Huber threshold in truncated-TSDF units),
    point_cell (frame 1's points: one per cube of this many MAP voxels)."""

    kind: str = "splat"
    factor: int = 2
    levels: tuple[tuple[float, float, int], ...] = ((0.7, 0.1, 3),)
    damping: float = 1e-3
    max_step: tuple[float, float] = (0.05, 1.0)
    truncation: float = 3.0
    iterations: int = 10
    robust: float = 0.2
    point_cell: float = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "levels", tuple((float(s), float(r), int(n)) for s, r, n in self.levels))
        object.__setattr__(self, "max_step", (float(self.max_step[0]), float(self.max_step[1])))
        if self.kind not in FINE_KINDS:
            raise ValueError(f"FineAlignment: kind must be one of {FINE_KINDS}, got {self.kind!r}")
        if self.factor < 1:
            raise ValueError(f"FineAlignment: factor must be >= 1, got {self.factor}")
        if not self.levels or min(n for _, _, n in self.levels) < 1:
            raise ValueError(f"FineAlignment: levels need >= 1 iteration each, got {self.levels}")
        if self.iterations < 1 or self.truncation <= 0 or self.robust <= 0 or self.point_cell <= 0:
            raise ValueError("FineAlignment: iterations >= 1 and positive truncation, robust and point_cell, got "
                             f"{self.iterations}, {self.truncation}, {self.robust}, {self.point_cell}")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "factor": self.factor, "levels": [list(l) for l in self.levels],
                "damping": self.damping, "max_step": list(self.max_step), "truncation": self.truncation,
                "iterations": self.iterations, "robust": self.robust, "point_cell": self.point_cell}


class FineFrame:
    """One frame's data for the fine stage, in its own ref_t. volume: B×C×Z'×Y'×X' on the fine grid (splat:
    C 1, the occupancy; tsdf: C 2, the TSDF and `known`); tsdf also points B×M×3 and points_valid B×M.

    `volume` and `points` may be given as zero-argument callables (`points`' returning (points, points_valid)):
    each part is then built on first use and kept. Why: a stream's frame is frame 1 of one pair, which reads
    its points, and frame 0 of the next, which reads its TSDF; a single pair never builds frame 1's TSDF,
    most of the stage's cost."""

    __slots__ = ("_volume", "_points")

    def __init__(self, volume, points=None, points_valid: torch.Tensor | None = None) -> None:
        self._volume = volume
        self._points = points if points is None or callable(points) else (points, points_valid)

    @property
    def volume(self) -> torch.Tensor | None:
        if callable(self._volume):
            self._volume = self._volume()
        return self._volume

    def _point_parts(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        if callable(self._points):
            self._points = self._points()
        return (None, None) if self._points is None else self._points

    @property
    def points(self) -> torch.Tensor | None:
        return self._point_parts()[0]

    @property
    def points_valid(self) -> torch.Tensor | None:
        return self._point_parts()[1]


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


def fine_frame(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor, map_grid: GridConfig,
               config: FineAlignment) -> FineFrame:
    """One frame's FineFrame for `config` (depth B×V×H×W, pix_T_cam / cam_T_ref B×V×4×4, the module's map
    grid): its splat, or its TSDF (read when the frame is a pair's frame 0) and its points reduced to one per
    cube of `point_cell` map voxels (read as frame 1), each built on first use (FineFrame)."""
    grid = fine_grid(map_grid, config.factor)
    if config.kind == "splat":
        return FineFrame(fine_occupancy(depth, pix_T_cam, cam_T_ref, grid))

    def tsdf() -> torch.Tensor:  # B×2×Z'×Y'×X'
        return projective_tsdf(depth, pix_T_cam, cam_T_ref, grid, truncation_m=config.truncation * grid.voxel_size,
                               band_voxels=math.ceil(config.truncation) + 1)

    def points() -> tuple[torch.Tensor, torch.Tensor]:  # B×M×3, B×M
        xyz_ref, valid = views_points_in_ref(depth, pix_T_cam, cam_T_ref)  # B×N×3, B×N
        return cell_mean_points(xyz_ref, valid, map_grid, config.point_cell * map_grid.voxel_size)
    return FineFrame(tsdf, points)


def align_fine(estimate: torch.Tensor, reference: FineFrame | torch.Tensor, query: FineFrame | torch.Tensor,
               grid: GridConfig, config: FineAlignment) -> torch.Tensor:
    """estimate B×4×4 (ref0_T_ref1), the frames' FineFrames (ref0, ref1; a bare tensor is a splat volume)
    on the fine `grid` -> the estimate after the config's alignment: B×4×4."""
    reference = reference if isinstance(reference, FineFrame) else FineFrame(reference)
    query = query if isinstance(query, FineFrame) else FineFrame(query)
    if config.kind == "tsdf":
        if reference.volume is None or query.points is None:
            raise ValueError("align_fine: a TSDF stage needs frame 0's TSDF and frame 1's points (fine_frame); "
                             "a bare volume is a splat stage's")
        return align_points_to_tsdf(estimate, reference.volume, query.points, query.points_valid, grid, config)
    ref_volume, query_volume = reference.volume.to(estimate.dtype), query.volume.to(estimate.dtype)
    check_shape("reference", ref_volume, (estimate.shape[0], 1, *grid.shape_zyx))
    check_shape("query", query_volume, tuple(ref_volume.shape))
    E = estimate
    for sigma, robust, iterations in config.levels:
        E, _ = gauss_newton_refine(gaussian_blur3d(ref_volume, sigma), gaussian_blur3d(query_volume, sigma), E,
                                   grid, iterations=iterations, damping=config.damping, robust_scale=robust,
                                   max_step=config.max_step)
    return E


@full_precision  # poses and normal equations in float32 at least, under bf16 autocast
def align_points_to_tsdf(estimate: torch.Tensor, tsdf: torch.Tensor, points: torch.Tensor,
                         points_valid: torch.Tensor, grid: GridConfig, config: FineAlignment) -> torch.Tensor:
    """Gauss-Newton of frame 1's points against frame 0's TSDF (module doc).

    estimate: B×4×4 ref0_T_ref1; tsdf: B×2×Z×Y×X on `grid` (TSDF, known) in ref0; points: B×M×3 in ref1,
    points_valid: B×M -> B×4×4. A point counts where the TSDF is known at it and it lies inside the
    truncation band (|TSDF| < 0.99); an example with fewer than 6 such points keeps its estimate."""
    B = estimate.shape[0]
    check_shape("tsdf", tsdf, (B, 2, *grid.shape_zyx))
    check_shape("points", points, (B, None, 3))
    check_shape("points_valid", points_valid, tuple(points.shape[:2]))
    dtype = estimate.dtype
    tsdf, points = tsdf.to(dtype), points.to(dtype)
    h = grid.voxel_size
    # The point and its six central-difference neighbours (±h along x, y, z), sampled in one call.
    offsets = torch.cat([torch.zeros(1, 3, dtype=dtype, device=tsdf.device),
                         h * torch.eye(3, dtype=dtype, device=tsdf.device),
                         -h * torch.eye(3, dtype=dtype, device=tsdf.device)])  # 7×3
    mem = mem_T_ref(grid, dtype=dtype, device=tsdf.device).expand(B, 4, 4)
    eye = torch.eye(6, dtype=dtype, device=tsdf.device)
    E = estimate
    for _ in range(config.iterations):
        q = se3.apply(E, points)  # B×M×3 in ref0
        at = q.unsqueeze(1) + offsets[None, :, None, :]  # B×7×M×3
        samples = sample_volume_at(tsdf, se3.apply(mem, at.reshape(B, -1, 3)).reshape(B, 7, 1, -1, 3))  # B×2×7×1×M
        phi, known = samples[:, 0, :, 0], samples[:, 1, :, 0]  # B×7×M
        r = phi[:, 0]  # B×M
        # The gradient by central differences where both neighbours are known, one-sided where one is (at a
        # view's border or the band's edge; an unknown voxel holds 0, which a central difference would read as
        # a steep slope); a point needs each axis to have a known neighbour. Why not all six required: that
        # dropped the points at the views' borders and ended 1.5 × / 1.3 × ICP's mean errors on the report's 32
        # moving test pairs instead of 0.99 × / 0.95 × (docs/findings.md, "Egomotion").
        kn = known > 0.999  # B×7×M
        plus, minus = kn[:, 1:4], kn[:, 4:7]  # B×3×M
        central = (phi[:, 1:4] - phi[:, 4:7]) / (2 * h)
        forward, backward = (phi[:, 1:4] - r[:, None]) / h, (r[:, None] - phi[:, 4:7]) / h
        grad = torch.where(plus & minus, central, torch.where(plus, forward, torch.where(minus, backward,
                                                                                       torch.zeros_like(central))))
        grad = grad.transpose(1, 2)  # B×M×3
        use = points_valid & kn[:, 0] & (plus | minus).all(1) & (r.abs() < 0.99)  # B×M
        w = torch.where(r.abs() <= config.robust, torch.ones_like(r), config.robust / r.abs().clamp_min(1e-12))
        w = w * use.to(dtype)  # B×M
        J = torch.cat([torch.cross(q, grad, dim=-1), grad], -1)  # B×M×6: r(exp(δ)·E·p) ≈ r + J·δ, δ = (ω, t)
        H = torch.einsum("bmi,bm,bmj->bij", J, w, J)  # B×6×6
        g = torch.einsum("bmi,bm,bm->bi", J, w, r)  # B×6
        diag = torch.diagonal(H, dim1=1, dim2=2)  # B×6
        A = H + config.damping * torch.diag_embed(diag) + 1e-6 * (diag.mean(1, keepdim=True)[..., None] + 1e-3) * eye
        delta = -torch.linalg.solve(A, g.unsqueeze(-1)).squeeze(-1)  # B×6
        delta = torch.where((use.sum(1) >= 6)[:, None], delta, torch.zeros_like(delta))
        delta = torch.cat([clamp_norm(delta[:, :3], config.max_step[0]), clamp_norm(delta[:, 3:], config.max_step[1])], 1)
        E = se3.from_rt(se3.axis_angle_to_matrix(delta[:, :3]), delta[:, 3:]) @ E
    return E

