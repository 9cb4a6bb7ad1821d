"""Synthetic rigid motions of a single feature volume: the supervised half of 3D flow training.

Conventions (docs/conventions.md#3d-flow): poses 4×4, `ref` metres, `mem` voxel coordinates (integer = centre);
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
from core.geometry.resample import warp_rigid

MOTION_RANGES = {"large": (6.0, 1.0), "small": (1.0, 0.1), "zero": (0.0, 0.0)}  # (degrees, metres)
# The motions of re-unprojected synthetic pairs (core.tasks.flow, `reproject_fraction`): zero motion gives an
# identical pair there, so its third is a jitter at the egomotion module's error scale (~0.01° / 3 mm mean
# on held-out static-camera pairs) instead: a pose off by that much re-voxelises the scene (README, "Which
# voxels move"), and the flow must read that as the tiny rigid motion it is.
REPROJECT_RANGES = {"large": (6.0, 1.0), "small": (1.0, 0.1), "jitter": (0.05, 0.01)}


def sample_motions(B: int, *, generator: torch.Generator | None = None, dtype=torch.float32, device=None,
                   ranges: dict[str, tuple[float, float]] = MOTION_RANGES) -> tuple[torch.Tensor, list[str]]:
    """B motions B×4×4 and their kinds, cycling through `ranges`' kinds (large/small/zero by default) from a
    random start (equal shares); each kind's rotation about each axis and translation along each axis
    uniform within its (degrees, metres)."""
    kinds = list(ranges)
    start = int(torch.randint(len(kinds), (1,), generator=generator))
    names = [kinds[(start + i) % len(kinds)] for i in range(B)]
    deg = torch.tensor([ranges[n][0] for n in names], dtype=torch.float64)
    met = torch.tensor([ranges[n][1] for n in names], dtype=torch.float64)
    u = torch.rand(B, 6, generator=generator, dtype=torch.float64) * 2.0 - 1.0  # B×6 in [-1, 1]
    angles = u[:, :3] * deg[:, None] * (math.pi / 180.0)
    R = se3.euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2])  # B×3×3
    M = se3.from_rt(R, u[:, 3:] * met[:, None])  # B×4×4
    return M.to(dtype=dtype, device=device), names


def rigid_flow(motion: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """motion B×4×4 (ref, applied to the scene) -> flow B×3×Z×Y×X in voxels of `grid`."""
    B = motion.shape[0]
    dtype, device = motion.dtype, motion.device
    memM = se3.compose(se3.compose(mem_T_ref(grid, dtype=dtype, device=device), motion),
                       ref_T_mem(grid, dtype=dtype, device=device))  # B×4×4
    p = voxel_centers_mem(grid, dtype=dtype, device=device).expand(B, -1, 3)  # B×ZYX×3
    moved = se3.apply(memM, p)  # B×ZYX×3
    flow = (moved - p).reshape(B, grid.Z, grid.Y, grid.X, 3)  # B×Z×Y×X×3
    return flow.permute(0, 4, 1, 2, 3).contiguous()  # B×3×Z×Y×X


def sample_object_motions(B: int, grid: GridConfig, *, generator: torch.Generator | None = None,
                          max_deg: float = 6.0, max_m: float = 1.5, dtype=torch.float32,
                          device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Object-like synthetic motions: a random axis-aligned block of the grid moves, the rest stays.

    Blocks span 10-25% of the grid along x and z and 25-50% along y, anywhere inside it; each block
    turns about its own vertical axis through its centre by ±`max_deg` (yaw) and shifts by ±`max_m` along
    x and z (±`max_m`/10 along y). Why: the paper's synthetic motions move the whole volume, so a module
    trained on them alone learns global motion and, measured on tiny, predicted ~0 for the cars of real
    pairs; a moving block is the same self-supervised signal at an object's scale.
    Returns (motion B×4×4 in ref, applied to the block's content; block B×1×Z×Y×X float {0,1}).
    """
    u = torch.rand(B, 12, generator=generator, dtype=torch.float64)  # B×12 in [0, 1)
    counts = torch.tensor([grid.X, grid.Y, grid.Z], dtype=torch.float64)  # (x, y, z)
    frac_lo, frac_hi = torch.tensor([0.10, 0.25, 0.10]), torch.tensor([0.25, 0.50, 0.25])
    size = torch.clamp((frac_lo + (frac_hi - frac_lo) * u[:, 0:3]) * counts, min=1.0)  # B×3 voxels
    lo = u[:, 3:6] * (counts - size)  # B×3 block start in mem (voxel-centre units)
    centre_mem = lo + size / 2 - 0.5  # B×3
    centre_ref = se3.apply(ref_T_mem(grid, dtype=torch.float64), centre_mem)  # B×3
    yaw = (u[:, 6] * 2 - 1) * math.radians(max_deg)
    t = (u[:, 7:10] * 2 - 1) * torch.tensor([max_m, max_m / 10, max_m], dtype=torch.float64)  # B×3
    eye = torch.eye(3, dtype=torch.float64).expand(B, 3, 3)
    to_centre, from_centre = se3.from_rt(eye, centre_ref), se3.from_rt(eye, -centre_ref)
    M = se3.from_rt(eye, t) @ to_centre @ se3.from_rt(se3.yaw_to_matrix(yaw), torch.zeros(B, 3, dtype=torch.float64)) @ from_centre
    p = voxel_centers_mem(grid, dtype=torch.float64).reshape(1, -1, 3)  # 1×ZYX×3
    inside = ((p >= lo[:, None] - 0.5) & (p < lo[:, None] + size[:, None] - 0.5)).all(-1)  # B×ZYX
    block = inside.reshape(B, 1, grid.Z, grid.Y, grid.X)  # B×1×Z×Y×X
    return M.to(dtype=dtype, device=device), block.to(dtype=dtype, device=device)


def landing_place(block: torch.Tensor, motion: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """Where `block` B×1×Z×Y×X lands after `motion` B×4×4 (ref, applied to its content): B×1×Z×Y×X bool."""
    return warp_rigid(block, se3.invert(motion), grid) > 0.5


def move_block(vol: torch.Tensor, motion: torch.Tensor, block: torch.Tensor, grid: GridConfig, *,
               vacate: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """The volume after only `block` moved by `motion`, and its flow.

    vol B×C×Z×Y×X, motion B×4×4, block B×1×Z×Y×X -> (vol1 B×C×Z×Y×X, flow B×3×Z×Y×X): vol1 holds the
    moved block where it landed and vol elsewhere; the vacated space (block, not landed on) keeps the old
    content, as occluded background would in a feature map, or with `vacate` is zero (an input volume:
    no points there, mid-grey colour, i.e. what a view that sees nothing there gives). flow is
    rigid_flow(motion) inside the block at t and 0 elsewhere, so warp_flow(vol1, flow) = vol on the block
    (where it stays inside the grid) and off the landing place.
    """
    moved = warp_rigid(vol, se3.invert(motion), grid)  # B×C×Z×Y×X
    landed = landing_place(block, motion, grid)  # B×1×Z×Y×X
    rest = torch.where(block > 0.5, torch.zeros_like(vol), vol) if vacate else vol
    vol1 = torch.where(landed, moved, rest)
    return vol1, rigid_flow(motion, grid) * block
