"""One 4-channel input volume per time step for the egomotion module: all views of the rig fused.

Each view is lifted into the frame's own `ref_t` with the rig calibration (cam_T_ref_t from poses at the
SAME time t, which a rig knows), never across time: the motion between ref0 and ref1 is what the module
estimates. Fusion: occupancy = max over views; RGB = average over the views that see the voxel.
`occupancy` picks binary or splatted (continuous) occupancy per view (core.models.input_volume); with
splats the max over views matters: a sum would double the surface density where views overlap, seams
that move with the camera (measured: the optimum of dense alignment of summed splats lies 0.0031 rad /
0.057 m off the truth on the small preset's moving-camera test pairs, of the max 0.0012 rad / 0.026 m;
tests/benchmarks/bench_egomotion_precision.py --floors).
`egomotion_input_volume` builds the volume an egomotion module expects (its grid and occupancy kind);
`egomotion_fine_frame` what its fine stage aligns at inference (core.models.egomotion_fine).
"""

from __future__ import annotations

import torch

from core.errors import check_shape
from core.geometry.grid import GridConfig
from core.models.egomotion_fine import FineFrame, fine_frame
from core.models.input_volume import input_volume


def fused_input_volume(rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                       cam_T_ref: torch.Tensor, grid: GridConfig, *, occupancy: str = "binary") -> torch.Tensor:
    """rgb: B×V×3×H×W in [0,1]; depth: B×V×H×W; pix_T_cam, cam_T_ref: B×V×4×4 -> B×4×Z×Y×X."""
    B, V, _, H, W = rgb.shape
    check_shape("depth", depth, (B, V, H, W))
    check_shape("cam_T_ref", cam_T_ref, (B, V, 4, 4))
    vol, in_view = input_volume(rgb.reshape(B * V, 3, H, W), depth.reshape(B * V, H, W),
                                pix_T_cam.reshape(B * V, 4, 4), cam_T_ref.reshape(B * V, 4, 4), grid,
                                occupancy=occupancy)
    vol = vol.reshape(B, V, 4, *grid.shape_zyx)  # B×V×4×Z×Y×X
    in_view = in_view.reshape(B, V, 1, *grid.shape_zyx)  # B×V×1×Z×Y×X
    occupancy = vol[:, :, :1].amax(dim=1)  # B×1×Z×Y×X
    rgb_vol = (vol[:, :, 1:] * in_view).sum(1) / in_view.sum(1).clamp_min(1.0)  # B×3×Z×Y×X
    return torch.cat([occupancy, rgb_vol], dim=1)


def egomotion_input_volume(net, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                           cam_T_ref: torch.Tensor) -> torch.Tensor:
    """`fused_input_volume` on an egomotion module's grid with its occupancy kind (`net.input_occupancy`;
    modules from before that option read binary occupancy). Shapes as fused_input_volume."""
    return fused_input_volume(rgb, depth, pix_T_cam, cam_T_ref, net.grid,
                              occupancy=getattr(net, "input_occupancy", "binary"))


def egomotion_fine_frame(net, depth: torch.Tensor, pix_T_cam: torch.Tensor,
                         cam_T_ref: torch.Tensor) -> FineFrame | None:
    """One frame's data for an egomotion module's fine stage (core.models.egomotion_fine.fine_frame with the
    module's grid and stage; depth B×V×H×W, pix_T_cam / cam_T_ref B×V×4×4), or None when the module has no
    fine stage (or is training: the stage runs at inference only). Its parts are built when the stage reads
    them (FineFrame)."""
    if net.fine_grid is None or net.training:
        return None
    return fine_frame(depth, pix_T_cam, cam_T_ref, net.grid, net.fine)
