"""Anchors of the detector's bird's-eye-view head: a few car-like axis-aligned boxes per coarse cell.

Conventions (docs/conventions.md#boxes): `ref` is X right, Y down, Z forward (metres); the map is B×F×Z×Y×X.
The head sees the map pooled by `stride` voxels in every axis and flattened along Y, i.e. one cell
per (z, x) column of `stride`×`stride` voxels. Each cell carries A anchors, rows (x, y, z, lx, ly, lz)
(axis-aligned, see detector_boxes), centred on the cell in x and z and at a fixed height `y_centre`
(objects stand on the ground; the y delta regresses the rest). Order: cell-major in (z, x), then the
A sizes — the order the head's outputs are flattened in (B×A×Zc×Xc -> B×Zc×Xc×A -> B×N).
"""

from __future__ import annotations

import torch

from core.errors import ShapeError
from core.geometry.grid import GridConfig


def coarse_shape(grid: GridConfig, stride: int) -> tuple[int, int, int]:
    """(Zc, Yc, Xc) of the map pooled by `stride`; ShapeError unless every count divides evenly."""
    if stride < 1 or any(n % stride for n in grid.shape_zyx):
        raise ShapeError(f"detector stride {stride} must divide the grid counts Z, Y, X = {grid.shape_zyx}")
    return (grid.Z // stride, grid.Y // stride, grid.X // stride)


def anchor_grid(grid: GridConfig, *, stride: int, sizes: tuple[tuple[float, float, float], ...],
                y_centre: float, device: torch.device | str | None = None) -> torch.Tensor:
    """All anchors of the head in `ref`: N×6 with N = Zc·Xc·A (order: see module doc).

    sizes: A rows (lx, ly, lz) in metres; y_centre: the anchors' centre height in ref (metres).
    """
    Zc, _, Xc = coarse_shape(grid, stride)
    cell = stride * grid.voxel_size
    z = grid.zmin + (torch.arange(Zc, dtype=torch.float32, device=device) + 0.5) * cell  # Zc
    x = grid.xmin + (torch.arange(Xc, dtype=torch.float32, device=device) + 0.5) * cell  # Xc
    zz, xx = torch.meshgrid(z, x, indexing="ij")                                          # Zc×Xc
    A = len(sizes)
    centres = torch.stack([xx, torch.full_like(xx, y_centre), zz], dim=-1)                # Zc×Xc×3
    lengths = torch.tensor(sizes, dtype=torch.float32, device=device)                     # A×3
    anchors = torch.cat([centres[:, :, None, :].expand(Zc, Xc, A, 3),
                         lengths.expand(Zc, Xc, A, 3)], dim=-1)                           # Zc×Xc×A×6
    return anchors.reshape(Zc * Xc * A, 6)                                                # N×6
