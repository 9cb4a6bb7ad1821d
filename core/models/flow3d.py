"""3D imagination flow: PWC-style coarse-to-fine 3D flow between two egomotion-stabilised feature maps.

Conventions (DESIGN.md §2): feature volumes B×F×Z×Y×X in the SAME frame (`ref` at t, the second map
already registered into it); flow volumes B×3×Z×Y×X, channels (x, y, z), voxel units, from t to t+1:
    f1(p + flow(p)) ≈ f0(p).

Per level l = finest..finest+levels-1 (coarsest first; level l has 2^l-times coarser voxels, from
average pooling; by default, as in PWC-Net, the finest decoder runs at half resolution (`finest=1`) and
its flow is upsampled to the grid, which costs 8× less than a full-resolution decoder. At coarse grids
(tiny: 1 m voxels, cars ~4×2×2 voxels) half resolution blurs a car into the static background around
it, so `finest=0` runs the last decoder on the grid itself):
1. upsample the coarser level's flow (trilinear, values scaled by the size ratio per axis);
2. warp the level's second pyramid volume by it (backward warp `warp_flow`; PWC's incremental warping);
3. local 3D cost volume (cross-correlation within ±radius voxels) between the first volume and the warp;
4. a small 3D conv decoder on [cost, first volume, upsampled flow] predicts a residual; flow = up + res.
The pyramid comes from a small learned 3D conv on the input features, then average pooling, so the
coarse voxels of level l are exactly the 2^l blocks of the grid and flow upsampling needs no offset.
The last conv of each decoder starts at zero: an untrained module predicts zero motion.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import check_shape
from core.geometry.resample import warp_flow
from core.models.cost_volume import cross_correlation_3d


def upsample_flow(flow: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """flow B×3×z×y×x (voxels of the coarse level) -> B×3×Z×Y×X at `size`, values in fine voxels.

    Each channel is scaled by its own axis ratio (x by X/x, y by Y/y, z by Z/z).
    """
    _, _, z, y, x = flow.shape
    Z, Y, X = size
    up = F.interpolate(flow, size=size, mode="trilinear", align_corners=False)  # B×3×Z×Y×X
    scale = torch.tensor([X / x, Y / y, Z / z], dtype=flow.dtype, device=flow.device).view(1, 3, 1, 1, 1)
    return up * scale


def downsample_flow(flow: torch.Tensor, size: tuple[int, int, int]) -> torch.Tensor:
    """flow B×3×Z×Y×X -> B×3×z×y×x (average over each coarse voxel, values in coarse voxels)."""
    Z, Y, X = flow.shape[-3:]
    z, y, x = size
    down = F.adaptive_avg_pool3d(flow, size)  # B×3×z×y×x
    scale = torch.tensor([x / X, y / Y, z / Z], dtype=flow.dtype, device=flow.device).view(1, 3, 1, 1, 1)
    return down * scale


def level_sizes(size: tuple[int, int, int], levels: int) -> list[tuple[int, int, int]]:
    """Sizes of the pyramid, finest first: each level halves every axis (ceil), never below 1."""
    sizes = [tuple(size)]
    for _ in range(levels - 1):
        sizes.append(tuple(max(1, (n + 1) // 2) for n in sizes[-1]))
    return sizes


class Flow3D(nn.Module):
    """(f0, f1): B×F×Z×Y×X each -> flow B×3×Z×Y×X (plus the per-level flows, coarse to fine)."""

    def __init__(self, *, in_channels: int = 32, channels: int = 16, levels: int = 3,
                 radius: tuple[int, int, int] = (1, 1, 1), hidden: int = 32, finest: int = 1) -> None:
        super().__init__()
        if finest not in (0, 1):
            raise ValueError(f"Flow3D: finest must be 0 (grid) or 1 (half resolution), got {finest}")
        self.finest = int(finest)
        self.in_channels, self.channels, self.levels, self.hidden = in_channels, channels, levels, hidden
        self.radius = tuple(int(r) for r in radius)
        self.features = nn.Sequential(
            nn.Conv3d(in_channels, channels, 3, padding=1), nn.LeakyReLU(0.1),
            nn.Conv3d(channels, channels, 3, padding=1))
        n_disp = (2 * self.radius[0] + 1) * (2 * self.radius[1] + 1) * (2 * self.radius[2] + 1)
        self.decoders = nn.ModuleList()
        for _ in range(levels):
            dec = nn.Sequential(
                nn.Conv3d(n_disp + channels + 3, hidden, 3, padding=1), nn.LeakyReLU(0.1),
                nn.Conv3d(hidden, hidden, 3, padding=1), nn.LeakyReLU(0.1),
                nn.Conv3d(hidden, 3, 3, padding=1))
            nn.init.zeros_(dec[-1].weight)
            nn.init.zeros_(dec[-1].bias)
            self.decoders.append(dec)

    def config(self) -> dict:
        return {"in_channels": self.in_channels, "channels": self.channels, "levels": self.levels,
                "radius": list(self.radius), "hidden": self.hidden, "finest": self.finest}

    def forward(self, f0: torch.Tensor, f1: torch.Tensor) -> dict[str, torch.Tensor | list[torch.Tensor]]:
        """f0, f1: B×F×Z×Y×X (same frame) -> {"flow": B×3×Z×Y×X (grid resolution),
        "levels": [B×3×z_l×y_l×x_l] per decoder, coarse first, in each level's own voxel units}."""
        check_shape("f0", f0, (None, self.in_channels, None, None, None))
        check_shape("f1", f1, tuple(f0.shape))
        B = f0.shape[0]
        c = self.features(torch.cat([f0, f1], dim=0))  # 2B×C×Z×Y×X
        sizes = level_sizes(tuple(f0.shape[-3:]), self.finest + self.levels)  # grid, then coarser
        pyramid = [c] + [F.adaptive_avg_pool3d(c, s) for s in sizes[1:]]  # finest first
        flow = None
        per_level = []
        for level in reversed(range(self.finest, self.finest + self.levels)):
            c0, c1 = pyramid[level][:B], pyramid[level][B:]  # B×C×z×y×x each
            if flow is None:
                up = c0.new_zeros(B, 3, *sizes[level])
                warped = c1
            else:
                up = upsample_flow(flow, sizes[level])  # B×3×z×y×x
                warped = warp_flow(c1, up)
            cost = F.leaky_relu(cross_correlation_3d(c0, warped, self.radius, normalize=True), 0.1)
            flow = up + self.decoders[level - self.finest](torch.cat([cost, c0, up], dim=1))  # B×3×z×y×x
            per_level.append(flow)
        return {"flow": upsample_flow(flow, sizes[0]), "levels": per_level}
