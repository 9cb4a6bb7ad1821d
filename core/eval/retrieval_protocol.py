"""Feature tensors for the paper's 2D and 3D retrieval protocol (appendix "2D and 3D Correspondence"),
built from one time step of a batch with a bundle's modules, composed as in core.tasks.pretrain.

- 3D: two maps of the same scene in the same `ref_t` grid, one fused from the query views, one from
  the candidate views (disjoint view subsets); a query cube and its true match sit at the same voxel.
  Centres may be drawn where both maps observe the voxel and some view's depth points occupy it (cubes
  on surfaces, not in empty air).
- 2D: the map fused from every view but the target, rendered into the target camera by the projector
  (top-down), against the bottom-up 2D embedding of the target image (net2d) at the same pixels. A
  regression-pretrained bundle renders RGB (no net2d): its top-down RGB is compared with the target
  image itself, downsampled to the render size and centred (the regression head predicts colour − 0.5).
  Centres may be drawn at pixels with a depth return whose point lies in the grid (as the training step).

Shapes: batch as core.data.batch.records_to_batch (B = 1 here: one example); outputs are one example's
C×Z×Y×X / C×H×W tensors and Z×Y×X / H×W bool masks, as core.eval.retrieval.retrieval_pool takes them.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.camera import depth_to_points, scale_intrinsics
from core.geometry.grid import GridConfig
from core.models.latent_map import masked_average
from core.tasks.poses import cam_T_ref


def _check_views(V: int, *groups: list[int]) -> None:
    for g in groups:
        if not g or any(not 0 <= v < V for v in g):
            raise ShapeError(f"view subset {g} must be non-empty indices in [0, {V})")


@torch.no_grad()
def retrieval_features_3d(mapper, batch: dict[str, torch.Tensor], t: int, *, query_views: list[int],
                          candidate_views: list[int]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> (query map F×Z×Y×X, candidate map F×Z×Y×X, valid centres Z×Y×X bool) of example 0 at step t."""
    V = batch["rgb"].shape[2]
    _check_views(V, query_views, candidate_views)
    feats, in_view, occupied = mapper.encode_views(batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"],
                                                   cam_T_ref(batch, t, t))  # B×V×F×Z×Y×X, B×V×1×…, B×V×1×…
    query = masked_average(feats[:, query_views], in_view[:, query_views])              # B×F×Z×Y×X
    candidate = masked_average(feats[:, candidate_views], in_view[:, candidate_views])  # B×F×Z×Y×X
    valid = ((in_view[:, query_views].amax(1) > 0) & (in_view[:, candidate_views].amax(1) > 0)
             & (occupied.amax(1) > 0))                                                 # B×1×Z×Y×X
    return query[0], candidate[0], valid[0, 0]


def _valid_pixels(depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref_: torch.Tensor, grid: GridConfig,
                  size: tuple[int, int]) -> torch.Tensor:
    """depth B×H×W, pix_T_cam / cam_T_ref B×4×4 -> B×Hr×Wr bool: a depth return inside the grid
    (core.tasks.pretrain's rule for 2D samples, at the render size)."""
    B, H, W = depth.shape
    xyz_cam, valid = depth_to_points(depth, pix_T_cam)                  # B×(H·W)×3, B×(H·W)
    xyz_ref = se3.apply(se3.invert(cam_T_ref_), xyz_cam)                 # B×(H·W)×3
    lo = torch.tensor(grid.bounds_min, device=depth.device)
    hi = torch.tensor(grid.bounds_max, device=depth.device)
    inside = valid & ((xyz_ref >= lo) & (xyz_ref < hi)).all(dim=-1)      # B×(H·W)
    mask = inside.to(depth.dtype).reshape(B, 1, H, W)                    # B×1×H×W
    return F.interpolate(mask, size=size, mode="nearest")[:, 0] > 0.5   # B×Hr×Wr


@torch.no_grad()
def retrieval_features_2d(mapper, projector, net2d, batch: dict[str, torch.Tensor], t: int, *,
                          target: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """-> (top-down E×Hr×Wr, bottom-up E×Hr×Wr, valid centres Hr×Wr bool) of example 0 at step t.

    net2d None: the regression variant (top-down RGB vs the centred target image, E = 3)."""
    rgb, depth, pix = batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"]  # B×V×3×H×W, B×V×H×W, B×V×4×4
    B, V, _, H, W = rgb.shape
    inputs = [v for v in range(V) if v != target]
    _check_views(V, [target], inputs)
    poses = cam_T_ref(batch, t, t)                                                   # B×V×4×4
    feats, in_view, _ = mapper.encode_views(rgb[:, inputs], depth[:, inputs], pix[:, inputs], poses[:, inputs])
    top3d = masked_average(feats, in_view)                                           # B×F×Z×Y×X
    if net2d is not None:
        bottom = net2d(rgb[:, target])                                               # B×E×Hr×Wr
        Hr, Wr = bottom.shape[-2:]
    else:
        Hr, Wr = math.ceil(H / 2), math.ceil(W / 2)
        bottom = F.interpolate(rgb[:, target], size=(Hr, Wr), mode="area") - 0.5     # B×3×Hr×Wr
    top = projector(top3d, scale_intrinsics(pix[:, target], Wr / W, Hr / H), poses[:, target], Hr, Wr)
    if top.shape != bottom.shape:
        raise ShapeError(f"top-down render {tuple(top.shape)} and bottom-up features {tuple(bottom.shape)} differ: "
                         "the projector and the 2D net do not belong together")
    valid = _valid_pixels(depth[:, target], pix[:, target], poses[:, target], mapper.grid, (Hr, Wr))
    return top[0], bottom[0], valid[0]
