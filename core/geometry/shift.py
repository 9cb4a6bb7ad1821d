"""Integer voxel shifts of a volume: the same scene lifted into a grid whose origin moved by whole voxels.

Lifting points into a grid moved by −d voxels puts every point d voxels further along each axis, so
`shift_voxels(v, d)` is exactly that lift for everything that stays inside (what enters from outside the
old bounds is missing: zeros). Used to build view-contrastive positives across grid placements
(core.tasks.pretrain, `shift_positives`).
"""

from __future__ import annotations

import torch

from core.errors import check_shape


def shift_voxels(volume: torch.Tensor, offset_xyz: tuple[int, int, int]) -> torch.Tensor:
    """volume: B×C×Z×Y×X; offset_xyz: whole voxels (dx, dy, dz) -> B×C×Z×Y×X with
    out[..., z + dz, y + dy, x + dx] = volume[..., z, y, x] where that lies inside, zeros elsewhere."""
    check_shape("volume", volume, (None, None, None, None, None))
    out = torch.zeros_like(volume)
    src, dst = [slice(None)] * 2, [slice(None)] * 2
    for offset, size in zip(reversed(offset_xyz), volume.shape[2:]):  # (dz, Z), (dy, Y), (dx, X)
        offset = int(offset)
        if abs(offset) >= size:
            return out
        src.append(slice(max(0, -offset), size - max(0, offset)))
        dst.append(slice(max(0, offset), size - max(0, -offset)))
    out[tuple(dst)] = volume[tuple(src)]
    return out
