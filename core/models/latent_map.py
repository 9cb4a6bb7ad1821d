"""The latent 3D map: per-view features registered into `ref` and fused by a masked running average.

Each view is lifted into `ref` with its known pose (core.models.input_volume), encoded by the 3D
encoder-decoder, and the per-view feature volumes are averaged, each voxel over the views whose
frustum contains it. A voxel no view covers takes the plain mean over views (the encoders'
"imagination" there). The average is re-normalised to unit length so map features live on the same
sphere as single-view features (the contrastive margins assume that).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from core.errors import check_shape
from core.geometry.grid import GridConfig
from core.models.encoder3d import Encoder3D
from core.models.input_volume import input_volume
from core.models.normalize import l2_normalize_channels


def masked_average(features: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """features: B×V×F×Z×Y×X, masks: B×V×1×Z×Y×X in [0, 1] -> B×F×Z×Y×X unit-norm average.

    Voxels with zero total mask fall back to the unweighted mean over V.
    """
    total = masks.sum(dim=1, keepdim=True)                       # B×1×1×Z×Y×X
    weights = torch.where(total > 0, masks, torch.ones_like(masks))  # B×V×1×Z×Y×X
    mean = (features * weights).sum(dim=1) / weights.sum(dim=1)  # B×F×Z×Y×X
    return l2_normalize_channels(mean)


@dataclass
class RunningMap:
    """Streaming state of the masked running average: weighted feature sum and weight per voxel."""

    feature_sum: torch.Tensor  # B×F×Z×Y×X
    weight: torch.Tensor       # B×1×Z×Y×X

    @staticmethod
    def empty(B: int, F_: int, grid: GridConfig, *, device=None, dtype=torch.float32) -> "RunningMap":
        return RunningMap(torch.zeros(B, F_, *grid.shape_zyx, device=device, dtype=dtype),
                          torch.zeros(B, 1, *grid.shape_zyx, device=device, dtype=dtype))

    def update(self, features: torch.Tensor, mask: torch.Tensor) -> "RunningMap":
        """Add one registered view: features B×F×Z×Y×X, mask B×1×Z×Y×X. Returns the new state."""
        return RunningMap(self.feature_sum + features * mask, self.weight + mask)

    def features(self) -> torch.Tensor:
        """Current map B×F×Z×Y×X (unit norm where observed, 0 where never observed)."""
        return l2_normalize_channels(self.feature_sum / self.weight.clamp(min=1e-6))


class Mapper(nn.Module):
    """RGB-D views with poses -> latent 3D feature map in `ref` (B×F×Z×Y×X)."""

    def __init__(self, *, grid: GridConfig | dict, width: int = 64, feature_dim: int = 32, full_res: int = 0) -> None:
        super().__init__()
        self.grid = grid if isinstance(grid, GridConfig) else GridConfig.from_dict(grid)
        self.width, self.feature_dim, self.full_res = width, feature_dim, int(full_res)
        self.encoder = Encoder3D(in_channels=4, width=width, out_channels=feature_dim, full_res=full_res)

    def config(self) -> dict:
        return {"grid": self.grid.to_dict(), "width": self.width, "feature_dim": self.feature_dim,
                "full_res": self.full_res}

    def encode_views(self, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                     cam_T_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """rgb: B×V×3×H×W in [0,1]; depth: B×V×H×W; pix_T_cam, cam_T_ref: B×V×4×4.

        Returns (features B×V×F×Z×Y×X unit-norm, in_view B×V×1×Z×Y×X, occupancy B×V×1×Z×Y×X).
        """
        volume, in_view = self.lift_views(rgb, depth, pix_T_cam, cam_T_ref)  # B×V×4×Z×Y×X, B×V×1×Z×Y×X
        return self.encode_volumes(volume), in_view, volume[:, :, :1]

    def encode_volumes(self, volume: torch.Tensor) -> torch.Tensor:
        """Lifted views (`lift_views`) B×V×4×Z×Y×X -> their features B×V×F×Z×Y×X (unit norm), one
        batched encoder pass."""
        B, V = volume.shape[:2]
        zyx = self.grid.shape_zyx
        feats = self.encoder(volume.reshape(B * V, volume.shape[2], *zyx))  # (B·V)×F×Z×Y×X
        return feats.reshape(B, V, self.feature_dim, *zyx)  # B×V×F×Z×Y×X

    def lift_views(self, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                   cam_T_ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The encoder's input: every view lifted into `ref` (core.models.input_volume). Inputs as
        `encode_views` -> (volume B×V×4×Z×Y×X, in_view B×V×1×Z×Y×X)."""
        B, V, _, H, W = rgb.shape
        check_shape("depth", depth, (B, V, H, W))
        check_shape("pix_T_cam", pix_T_cam, (B, V, 4, 4))
        check_shape("cam_T_ref", cam_T_ref, (B, V, 4, 4))
        volume, in_view = input_volume(rgb.reshape(B * V, 3, H, W), depth.reshape(B * V, H, W),
                                       pix_T_cam.reshape(B * V, 4, 4), cam_T_ref.reshape(B * V, 4, 4),
                                       self.grid)  # (B·V)×4×Z×Y×X, (B·V)×1×Z×Y×X
        zyx = self.grid.shape_zyx
        return volume.reshape(B, V, 4, *zyx), in_view.reshape(B, V, 1, *zyx)

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                cam_T_ref: torch.Tensor) -> torch.Tensor:
        """Same inputs as `encode_views` -> fused map B×F×Z×Y×X."""
        feats, in_view, _ = self.encode_views(rgb, depth, pix_T_cam, cam_T_ref)
        return masked_average(feats, in_view)
