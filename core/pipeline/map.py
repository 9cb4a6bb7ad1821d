"""Map inference: RGB-D views with known poses -> 3D feature map, occupancy and a heightmap in `ref`.

`ref` is `world_T_ref` when given, else the camera of view 0 (docs/conventions.md#frames). Each view is lifted into
`ref` with cam_T_ref = inv(world_T_cam)·world_T_ref, encoded, and fused by the masked average of
the latent map (core.models.latent_map).
"""

from __future__ import annotations

import torch

from core.bundle import Bundle
from core.errors import check_shape
from core.geometry.grid import GridConfig
from core.geometry.poses import rig_cam_T_ref
from core.models.latent_map import masked_average


def heightmap_from_occupancy(occupancy: torch.Tensor, grid: GridConfig, threshold: float = 0.5) -> torch.Tensor:
    """occupancy: B×1×Z×Y×X probabilities -> B×Z×X metres above the grid floor (ref y = ymax, Y points
    down) of the top face of the highest voxel with P ≥ threshold; 0 where a column has none."""
    occ = occupancy[:, 0] >= threshold                                   # B×Z×Y×X
    Y = grid.Y
    y_idx = torch.arange(Y, device=occupancy.device).view(1, 1, Y, 1)   # 1×1×Y×1
    top = torch.where(occ, y_idx, torch.full_like(y_idx, Y)).amin(dim=2)  # B×Z×X, Y = empty column
    return (Y - top).to(occupancy.dtype if occupancy.is_floating_point() else torch.float32) * grid.voxel_size


@torch.no_grad()
def map_frames(bundle: Bundle, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
               world_T_cam: torch.Tensor, world_T_ref: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """rgb: B×V×3×H×W in [0,1]; depth: B×V×H×W metres (0 = missing); pix_T_cam, world_T_cam: B×V×4×4;
    world_T_ref: B×4×4 or None (camera of view 0).

    Returns {"features": B×F×Z×Y×X, "occupancy": B×1×Z×Y×X probabilities (if the bundle has an
    occupancy head), "heightmap": B×Z×X metres (with occupancy), "observed": B×1×Z×Y×X in {0,1}
    (voxels inside some view's frustum)}.
    """
    mapper = bundle.require("mapper")
    B, V = rgb.shape[:2]
    check_shape("rgb", rgb, (B, V, 3, None, None))
    check_shape("depth", depth, (B, V, rgb.shape[3], rgb.shape[4]))
    check_shape("pix_T_cam", pix_T_cam, (B, V, 4, 4))
    check_shape("world_T_cam", world_T_cam, (B, V, 4, 4))
    if world_T_ref is not None:
        check_shape("world_T_ref", world_T_ref, (B, 4, 4))
    cam_T_ref = rig_cam_T_ref(world_T_cam, world_T_ref)  # B×V×4×4
    feats, in_view, _ = mapper.encode_views(rgb, depth, pix_T_cam, cam_T_ref)
    out = {"features": masked_average(feats, in_view), "observed": in_view.amax(dim=1)}
    if "occupancy" in bundle.modules:
        occupancy = bundle.modules["occupancy"].probabilities(out["features"])  # B×1×Z×Y×X
        out["occupancy"] = occupancy
        out["heightmap"] = heightmap_from_occupancy(occupancy, mapper.grid)
    return out
