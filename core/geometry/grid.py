"""The map grid: metric bounds in `ref` plus voxel counts, and the ref <-> mem similarity.

Conventions (docs/conventions.md#the-map-grid): `ref` is a camera-like frame (X right, Y down, Z forward, metres);
`mem` holds voxel index coordinates (x, y, z) with integer values at voxel centres:
    mem = (ref - min) / voxel - 0.5
Volumes are laid out B×C×Z×Y×X; point sets are B×N×3 in (x, y, z) order. Voxels are cubic.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class GridConfig:
    """Axis-aligned box in `ref` split into Z×Y×X cubic voxels."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    zmin: float
    zmax: float
    Z: int
    Y: int
    X: int

    def __post_init__(self) -> None:
        if not (self.xmax > self.xmin and self.ymax > self.ymin and self.zmax > self.zmin):
            raise ValueError(f"grid bounds must be increasing, got {self}")
        if min(self.Z, self.Y, self.X) < 1:
            raise ValueError(f"grid counts must be positive, got Z={self.Z} Y={self.Y} X={self.X}")
        sizes = ((self.xmax - self.xmin) / self.X, (self.ymax - self.ymin) / self.Y,
                 (self.zmax - self.zmin) / self.Z)
        if max(sizes) - min(sizes) > 1e-6 * max(sizes):
            raise ValueError(f"voxels must be cubic, got sizes (x, y, z) = {sizes}")

    @property
    def voxel_size(self) -> float:
        """Edge length of one voxel in metres."""
        return (self.xmax - self.xmin) / self.X

    @property
    def shape_zyx(self) -> tuple[int, int, int]:
        return (self.Z, self.Y, self.X)

    @property
    def bounds_min(self) -> tuple[float, float, float]:
        """(xmin, ymin, zmin) in ref."""
        return (self.xmin, self.ymin, self.zmin)

    @property
    def bounds_max(self) -> tuple[float, float, float]:
        return (self.xmax, self.ymax, self.zmax)

    def scaled(self, factor: float) -> "GridConfig":
        """The same bounds with voxel counts multiplied by `factor` (0.5 halves resolution)."""
        return GridConfig(xmin=self.xmin, xmax=self.xmax, ymin=self.ymin, ymax=self.ymax,
                          zmin=self.zmin, zmax=self.zmax, Z=max(1, round(self.Z * factor)),
                          Y=max(1, round(self.Y * factor)), X=max(1, round(self.X * factor)))

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax", "Z", "Y", "X")}

    @staticmethod
    def from_dict(d: dict) -> "GridConfig":
        return GridConfig(**{k: d[k] for k in ("xmin", "xmax", "ymin", "ymax", "zmin", "zmax", "Z", "Y", "X")})


def mem_T_ref(grid: GridConfig, *, dtype: torch.dtype = torch.float32,
              device: torch.device | str | None = None) -> torch.Tensor:
    """4×4 similarity taking `ref` metres to `mem` voxel coordinates: mem = (ref - min)/voxel - 0.5."""
    s = 1.0 / grid.voxel_size
    m = torch.eye(4, dtype=dtype, device=device)
    m[0, 0] = m[1, 1] = m[2, 2] = s
    m[0, 3] = -grid.xmin * s - 0.5
    m[1, 3] = -grid.ymin * s - 0.5
    m[2, 3] = -grid.zmin * s - 0.5
    return m


def ref_T_mem(grid: GridConfig, *, dtype: torch.dtype = torch.float32,
              device: torch.device | str | None = None) -> torch.Tensor:
    """Inverse of `mem_T_ref`: voxel coordinates to `ref` metres."""
    v = grid.voxel_size
    m = torch.eye(4, dtype=dtype, device=device)
    m[0, 0] = m[1, 1] = m[2, 2] = v
    m[0, 3] = grid.xmin + 0.5 * v
    m[1, 3] = grid.ymin + 0.5 * v
    m[2, 3] = grid.zmin + 0.5 * v
    return m


def voxel_centers_mem(grid: GridConfig, *, dtype: torch.dtype = torch.float32,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """All voxel centres in `mem`, shape (Z*Y*X)×3 in (x, y, z) order, flattened in Z,Y,X order."""
    z, y, x = torch.meshgrid(torch.arange(grid.Z, dtype=dtype, device=device),
                             torch.arange(grid.Y, dtype=dtype, device=device),
                             torch.arange(grid.X, dtype=dtype, device=device), indexing="ij")
    return torch.stack([x, y, z], dim=-1).reshape(-1, 3)  # Z*Y*X×3


def voxel_centers_ref(grid: GridConfig, *, dtype: torch.dtype = torch.float32,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """All voxel centres in `ref` metres, shape (Z*Y*X)×3, flattened in Z,Y,X order."""
    mem = voxel_centers_mem(grid, dtype=dtype, device=device)
    return mem * grid.voxel_size + torch.tensor(grid.bounds_min, dtype=dtype, device=device) + 0.5 * grid.voxel_size
