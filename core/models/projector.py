"""3D->2D view projection: render a feature map of `ref` into a target camera (paper appendix).

One trilinear sampling takes the map into the camera's frustum at `depth_planes` log-spaced depths
(core.geometry.frustum.frustum_resample, B×C×D×H×W), then:
    max-pool 8 along depth (coarse aggregation along each ray),
    conv3d 3-1-H3 (LeakyReLU + BatchNorm),
    reshape rays into channels (H3·D/8),
    conv2d 3-1-H2 (LeakyReLU + BatchNorm),
    conv2d 1-1-E                                  (E = 3 renders RGB; E = 32 embeddings).
The output image size is whatever the caller asks (`H`, `W`); the pretraining task renders at half
the camera resolution (intrinsics scaled accordingly) to keep the frustum tensor affordable.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import ShapeError, check_shape
from core.geometry.frustum import frustum_resample
from core.geometry.grid import GridConfig
from core.models.normalize import l2_normalize_channels
from core.models.conv3d import Conv3d


class Projector(nn.Module):
    """Feature map B×C×Z×Y×X in `ref` + camera -> B×E×H×W image-plane features."""

    def __init__(self, *, grid: GridConfig | dict, in_channels: int = 32, out_channels: int = 32,
                 depth_planes: int = 64, depth_min: float = 1.0, depth_max: float = 40.0,
                 pool: int = 8, hidden3d: int = 32, hidden2d: int = 32, normalize: bool = True) -> None:
        super().__init__()
        self.grid = grid if isinstance(grid, GridConfig) else GridConfig.from_dict(grid)
        if depth_planes % pool:
            raise ShapeError(f"depth_planes ({depth_planes}) must be a multiple of pool ({pool})")
        self.in_channels, self.out_channels = in_channels, out_channels
        self.depth_planes, self.depth_min, self.depth_max, self.pool = depth_planes, depth_min, depth_max, pool
        self.hidden3d, self.hidden2d, self.normalize = hidden3d, hidden2d, normalize
        self.conv3d = nn.Sequential(Conv3d(in_channels, hidden3d, 3, padding=1),
                                    nn.LeakyReLU(0.1, inplace=True), nn.BatchNorm3d(hidden3d))
        self.conv2d = nn.Sequential(nn.Conv2d(hidden3d * (depth_planes // pool), hidden2d, 3, padding=1),
                                    nn.LeakyReLU(0.1, inplace=True), nn.BatchNorm2d(hidden2d))
        self.out = nn.Conv2d(hidden2d, out_channels, 1)

    def config(self) -> dict:
        return {"grid": self.grid.to_dict(), "in_channels": self.in_channels,
                "out_channels": self.out_channels, "depth_planes": self.depth_planes,
                "depth_min": self.depth_min, "depth_max": self.depth_max, "pool": self.pool,
                "hidden3d": self.hidden3d, "hidden2d": self.hidden2d, "normalize": self.normalize}

    def forward(self, feat_ref: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                H: int, W: int) -> torch.Tensor:
        """feat_ref: B×C×Z×Y×X map in `ref`; pix_T_cam: B×4×4 intrinsics *for an H×W image*;
        cam_T_ref: B×4×4 -> B×E×H×W (unit-norm per pixel if `normalize`)."""
        check_shape("feat_ref", feat_ref, (None, self.in_channels, self.grid.Z, self.grid.Y, self.grid.X))
        # float32 sampling: under bf16 autocast the map may arrive in bf16, too coarse for coordinates.
        frustum = frustum_resample(feat_ref.float(), pix_T_cam.float(), cam_T_ref.float(), self.grid, H, W,
                                   self.depth_planes, self.depth_min, self.depth_max)  # B×C×D×H×W
        return self.decode(frustum)

    def decode(self, frustum: torch.Tensor) -> torch.Tensor:
        """frustum: B×C×D×H×W (depth-plane samples) -> B×E×H×W."""
        check_shape("frustum", frustum, (None, self.in_channels, self.depth_planes, None, None))
        B, _, _, H, W = frustum.shape
        x = F.max_pool3d(frustum, kernel_size=(self.pool, 1, 1))  # B×C×D/8×H×W
        x = self.conv3d(x)                                         # B×H3×D/8×H×W
        x = x.reshape(B, -1, H, W)                                 # B×(H3·D/8)×H×W
        emb = self.out(self.conv2d(x))                             # B×E×H×W
        return l2_normalize_channels(emb) if self.normalize else emb
