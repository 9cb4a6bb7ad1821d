"""View-predictive pretraining step: contrastive (paper) or RGB regression (baseline).

One step, all at one time step t of each record (B×T×V views):
  1. pick a held-out target view v* (and t) at random; the other views are the inputs;
  2. lift every view into `ref` with its known pose (cam_T_ref = inv(world_T_cam)·world_T_ref) and
     encode it with the shared 3D encoder-decoder: the input views in one batched pass, the target in
     its own (as the authors' code: in training mode BatchNorm's batch statistics would otherwise carry
     the target into the map; regression without the matching term does not encode the target at all);
  3. top-down 3D = masked average of the input views' features (the latent map);
     bottom-up 3D = the target view's own features;
  4. top-down 2D = the map rendered into the target camera by the projector (at `render_scale` of
     the image size); bottom-up 2D = the 2D ResNet on the target image (stride 2 at half scale);
  5. losses: contrastive — 0.1·margin2D + 1.0·margin3D + 0.001·(L2 2D + L2 3D), sampled only where
     the target is observed (2D: pixels with depth whose point is inside the grid; 3D: voxels the
     target's rays reach — its occupied ∪ free voxels); regression — L1 between the RGB rendered from
     the map (E = 3) and the target image (downsampled to the render size), over the same valid pixels
     as the 2D contrastive term (as the authors' code: sky and what lies beyond the grid are in no input
     view's volume, ~28 % of the pixels at small).
     Both objectives also train the occupancy head on the map, with labels from all V views
     (occupied = voxelised points, free = ray traversal), class-balanced.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.camera import depth_to_points, scale_intrinsics
from core.geometry.freespace import free_space
from core.geometry.grid import GridConfig
from core.geometry.shift import shift_voxels
from core.losses.contrastive import ContrastiveConfig, view_contrastive_loss
from core.losses.dense import dense_l2
from core.losses.local_matching import local_matching_loss
from core.losses.local_negatives import local_negative_loss
from core.losses.occupancy import balanced_occupancy_loss, occupancy_accuracy
from core.losses.regression import rgb_l1
from core.models.flow_synthetic import landing_place, move_block, sample_object_motions
from core.models.latent_map import Mapper, masked_average
from core.models.net2d import Net2D
from core.models.occupancy_head import OccupancyHead
from core.models.projector import Projector
from core.presets import Preset
from core.tasks import poses

OBJECTIVES = ("contrastive", "regression")


@dataclass(frozen=True)
class PretrainConfig:
    """Everything the pretraining step needs besides the batch (built from a preset by `from_preset`)."""

    grid: GridConfig
    objective: str = "contrastive"
    feature_dim: int = 32          # F
    embed_dim: int = 32            # E (contrastive); the regression head always renders 3 channels
    encoder_width: int = 64        # C of the 3D encoder; the 2D ResNet uses (C, 2C)
    encoder_full_res: int = 0      # Encoder3D.full_res: channels of its full-resolution branch
    depth_planes: int = 64
    depth_min: float = 1.0
    depth_max: float = 40.0
    render_scale: float = 0.5      # projector output size relative to the camera image (1.0 or 0.5)
    contrastive: ContrastiveConfig = field(default_factory=ContrastiveConfig)
    coeff_2d: float = 0.1
    coeff_3d: float = 1.0
    coeff_l2: float = 0.001
    coeff_occ: float = 1.0
    coeff_rgb: float = 1.0
    free_space_stride: int = 2     # trace free-space rays from every n-th pixel per axis (labels only;
                                   # neighbouring rays cross the same voxels, tracing is the step's cost)
    # Local matching term (core.losses.local_matching; either objective; 0 = off): weight, window radius
    # (x, y, z voxels), softmax temperature, sampled voxels per example.
    coeff_match: float = 0.0
    match_radius: tuple[int, int, int] = (2, 1, 2)
    match_temperature: float = 0.1
    match_samples: int = 256
    # Local negatives of the 3D contrastive loss (core.losses.local_negatives; contrastive only; 0 = off, the
    # paper's): weight, neighbour radius in voxels.
    coeff_local_negatives: float = 0.0
    local_negative_radius: int = 2
    # 3D positives across grid placements (contrastive only; 0 = off, the paper's aligned maps): the target
    # view's volume is lifted into a grid moved by a random whole-voxel offset within ±N per axis, and its
    # features are moved back before the 3D contrastive terms. Why: with both maps on one grid, features
    # that change only every 8 voxels (the encoder's coarse path) satisfy the loss, and they do not follow
    # content moved by 1-3 voxels (tests/benchmarks/bench_flow_features.py, the scene-shift test).
    shift_positives: int = 0
    seed: int | None = None        # view selection / sampling RNG; None uses torch's global RNG

    def __post_init__(self) -> None:
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")
        if self.render_scale not in (0.5, 1.0):
            raise ValueError(f"render_scale must be 0.5 or 1.0, got {self.render_scale}")
        if self.coeff_local_negatives > 0 and self.objective != "contrastive":
            raise ValueError("coeff_local_negatives needs objective='contrastive' (regression has no negatives)")
        if self.shift_positives < 0:
            raise ValueError(f"shift_positives must be >= 0 voxels, got {self.shift_positives}")
        if self.shift_positives > 0 and self.objective != "contrastive":
            raise ValueError("shift_positives needs objective='contrastive' (regression has no 3D positives)")
        if self.local_negative_radius < 1:
            raise ValueError(f"local_negative_radius must be >= 1 voxel, got {self.local_negative_radius}")


class PretrainTask(nn.Module):
    """`forward(batch) -> {"loss", metrics…}`; `exported_modules()` names the parts a bundle keeps."""

    def __init__(self, *, config: PretrainConfig) -> None:
        super().__init__()
        self.cfg = c = config
        self.mapper = Mapper(grid=c.grid, width=c.encoder_width, feature_dim=c.feature_dim,
                             full_res=c.encoder_full_res)
        contrastive = c.objective == "contrastive"
        self.projector = Projector(grid=c.grid, in_channels=c.feature_dim,
                                   out_channels=c.embed_dim if contrastive else 3,
                                   depth_planes=c.depth_planes, depth_min=c.depth_min, depth_max=c.depth_max,
                                   normalize=contrastive)
        self.net2d = (Net2D(in_channels=3, widths=(c.encoder_width, 2 * c.encoder_width),
                            out_channels=c.embed_dim, stride=2 if c.render_scale == 0.5 else 1)
                      if contrastive else None)
        self.occupancy = OccupancyHead(in_channels=c.feature_dim)
        self._generator = torch.Generator().manual_seed(c.seed) if c.seed is not None else None

    @staticmethod
    def from_preset(preset: Preset, *, objective: str = "contrastive", **overrides) -> "PretrainTask":
        """Task at a preset's sizes; keyword `overrides` replace PretrainConfig fields."""
        base = dict(grid=preset.grid, objective=objective, feature_dim=preset.feature_dim,
                    embed_dim=preset.embed_dim, encoder_width=preset.encoder_width,
                    encoder_full_res=preset.encoder_full_res,
                    depth_planes=preset.depth_planes, depth_min=preset.depth_min, depth_max=preset.depth_max,
                    contrastive=ContrastiveConfig(samples=preset.train.contrastive_samples))
        base.update(overrides)
        return PretrainTask(config=PretrainConfig(**base))

    def exported_modules(self) -> dict[str, nn.Module]:
        mods = {"mapper": self.mapper, "projector": self.projector, "occupancy": self.occupancy}
        if self.net2d is not None:
            mods["net2d"] = self.net2d
        return mods

    def _randint(self, n: int) -> int:
        return int(torch.randint(n, (1,), generator=self._generator).item())

    def _positive_offset(self) -> tuple[int, int, int]:
        """(dx, dy, dz) whole voxels, each uniform in ±shift_positives; (0, 0, 0) when off (no draw)."""
        s = self.cfg.shift_positives  # > 0 only with the contrastive objective (PretrainConfig refuses it otherwise)
        if s == 0:
            return (0, 0, 0)
        return tuple(self._randint(2 * s + 1) - s for _ in range(3))

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """batch: `core.data.batch.records_to_batch` output (B×T×V views, V ≥ 2) -> loss + metrics."""
        rgb_all = batch["rgb"]  # B×T×V×3×H×W
        _, T, V, _, H, W = rgb_all.shape
        if V < 2:
            raise ShapeError(f"pretraining needs at least 2 views per time step, got V={V}")
        t, target = self._randint(T), self._randint(V)
        inputs = [v for v in range(V) if v != target]
        rgb, depth = rgb_all[:, t], batch["depth"][:, t]          # B×V×3×H×W, B×V×H×W
        pix_T_cam = batch["pix_T_cam"]                             # B×V×4×4
        cam_T_ref = poses.cam_T_ref(batch, t, t)                  # B×V×4×4

        # encode_views in two steps: the matching term below reuses the target's lifted volume
        volume, in_view = self.mapper.lift_views(rgb, depth, pix_T_cam, cam_T_ref)  # B×V×4×Z×Y×X, B×V×1×Z×Y×X
        occupied = volume[:, :, :1]                                     # B×V×1×Z×Y×X, on the unshifted grid
        offset = self._positive_offset()
        if offset != (0, 0, 0):  # the target view lifted into the moved grid (PretrainConfig.shift_positives)
            volume = torch.cat([volume[:, :target], shift_voxels(volume[:, target], offset)[:, None],
                                volume[:, target + 1:]], dim=1)         # B×V×4×Z×Y×X
        # The input views and the target in separate encoder passes: in training mode BatchNorm normalises
        # by its batch's statistics, so one pass over all V views would pass the held-out target's
        # statistics (its colours, for regression) into the map it is predicted from. The target's own
        # features are needed only by the contrastive terms and the matching term.
        top3d = masked_average(self.mapper.encode_volumes(volume[:, inputs]), in_view[:, inputs])  # B×F×Z×Y×X
        needs_target = self.cfg.objective == "contrastive" or self.cfg.coeff_match > 0
        target_feats = (self.mapper.encode_volumes(volume[:, target:target + 1])[:, 0]
                        if needs_target else None)                      # B×F×Z×Y×X
        free = self._free_space(depth, pix_T_cam, cam_T_ref)         # B×V×1×Z×Y×X

        logits = self.occupancy(top3d)                                 # B×1×Z×Y×X
        occ_label = occupied.amax(dim=1)                               # B×1×Z×Y×X
        free_label = free.amax(dim=1)
        out: dict[str, torch.Tensor] = {"loss_occ": balanced_occupancy_loss(logits, occ_label, free_label)}
        out["occ_acc"] = occupancy_accuracy(logits.detach(), occ_label, free_label)

        pix_target, cam_target = pix_T_cam[:, target], cam_T_ref[:, target]  # B×4×4
        rgb_target = rgb[:, target]                                    # B×3×H×W
        Hr, Wr = (math.ceil(H / 2), math.ceil(W / 2)) if self.cfg.render_scale == 0.5 else (H, W)
        pix_render = scale_intrinsics(pix_target, Wr / W, Hr / H)
        top2d = self.projector(top3d, pix_render, cam_target, Hr, Wr)  # B×E×Hr×Wr
        # pixels the map can know: a depth return inside the grid (both objectives score only these)
        valid2d = self._valid_pixels(depth[:, target], pix_target, cam_target, (Hr, Wr))  # B×1×Hr×Wr

        if self.cfg.objective == "contrastive":
            bottom3d = target_feats                                    # B×F×Z×Y×X
            valid3d = torch.maximum(occupied[:, target], free[:, target])  # B×1×Z×Y×X
            if offset != (0, 0, 0):  # back onto the unshifted grid; voxels whose match left the grid are invalid
                back = tuple(-o for o in offset)
                bottom3d = shift_voxels(bottom3d, back)
                valid3d = valid3d * shift_voxels(torch.ones_like(valid3d), back)
            bottom2d = self.net2d(rgb_target)                          # B×E×Hr×Wr
            out["loss_3d"] = view_contrastive_loss(top3d, bottom3d, valid3d, self.cfg.contrastive, self._generator)
            out["loss_2d"] = view_contrastive_loss(top2d, bottom2d, valid2d, self.cfg.contrastive, self._generator)
            out["loss_l2_3d"] = dense_l2(top3d, bottom3d, valid3d)
            out["loss_l2_2d"] = dense_l2(top2d, bottom2d, valid2d)
            out["valid_3d"] = valid3d.float().mean()
            out["valid_2d"] = valid2d.float().mean()
            view_loss = (self.cfg.coeff_3d * out["loss_3d"] + self.cfg.coeff_2d * out["loss_2d"]
                         + self.cfg.coeff_l2 * (out["loss_l2_3d"] + out["loss_l2_2d"]))
            if self.cfg.coeff_local_negatives > 0:
                out["loss_local_neg"] = local_negative_loss(
                    top3d, bottom3d, valid3d, radius=self.cfg.local_negative_radius,
                    samples=self.cfg.contrastive.samples, beta=self.cfg.contrastive.beta,
                    margin=self.cfg.contrastive.margin, generator=self._generator)
                view_loss = view_loss + self.cfg.coeff_local_negatives * out["loss_local_neg"]
        else:
            target_small = F.interpolate(rgb_target, size=(Hr, Wr), mode="area")  # B×3×Hr×Wr
            # the head predicts centred colour; sky and what lies beyond the grid are not the map's to know
            out["rgb_l1"] = rgb_l1(top2d + 0.5, target_small, valid2d)
            view_loss = self.cfg.coeff_rgb * out["rgb_l1"]
        if self.cfg.coeff_match > 0:  # either objective: it trains the encoder only, on one view
            out["loss_match"], out["match_hit"] = self._local_matching(volume[:, target], target_feats)
            view_loss = view_loss + self.cfg.coeff_match * out["loss_match"]

        loss = view_loss + self.cfg.coeff_occ * out["loss_occ"]
        metrics = {k: v.detach().float() for k, v in out.items()}
        return {"loss": loss, **metrics}

    def _local_matching(self, volume: torch.Tensor, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The local matching term (core.losses.local_matching) on one view per example: an object-sized
        block of its input volume moves (core.models.flow_synthetic, the vacated voxels emptied), the
        moved volume is encoded, and each sampled occupied voxel's feature must find itself again where
        its content went, among that place's neighbours. Samples: half inside the block, half outside
        (those must stay put while something moves nearby); voxels the block landed on are skipped.
        volume: B×4×Z×Y×X, features: its encoding B×F×Z×Y×X -> (loss, hit rate) scalars."""
        g, B = self.cfg.grid, volume.shape[0]
        with torch.no_grad():
            motion, block = sample_object_motions(B, g, generator=self._generator, dtype=volume.dtype,
                                                  device=volume.device)  # B×4×4, B×1×Z×Y×X
            moved, flow = move_block(volume, motion, block, g, vacate=True)  # B×4×Z×Y×X, B×3×Z×Y×X
            landed = landing_place(block, motion, g)  # B×1×Z×Y×X
            occupied = volume[:, :1] > 0
            inside = occupied & (block > 0.5)
            outside = occupied & (block < 0.5) & ~landed
        moved_features = self.mapper.encoder(moved)  # B×F×Z×Y×X
        kwargs = dict(radius=self.cfg.match_radius, temperature=self.cfg.match_temperature,
                      samples=self.cfg.match_samples // 2, generator=self._generator)
        loss_in, hit_in = local_matching_loss(features, moved_features, flow, inside.to(volume.dtype), **kwargs)
        loss_out, _ = local_matching_loss(features, moved_features, flow, outside.to(volume.dtype), **kwargs)
        return loss_in + loss_out, hit_in

    def _free_space(self, depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor) -> torch.Tensor:
        """depth: B×V×H×W, pix_T_cam, cam_T_ref: B×V×4×4 -> free-space labels B×V×1×Z×Y×X."""
        B, V, H, W = depth.shape
        s = self.cfg.free_space_stride
        with torch.no_grad():
            xyz_cam, valid = depth_to_points(depth.reshape(B * V, H, W), pix_T_cam.reshape(B * V, 4, 4))
            xyz_cam = xyz_cam.reshape(B * V, H, W, 3)[:, ::s, ::s].reshape(B * V, -1, 3)  # (B·V)×N'×3
            valid = valid.reshape(B * V, H, W)[:, ::s, ::s].reshape(B * V, -1)            # (B·V)×N'
            free = free_space(xyz_cam, valid, cam_T_ref.reshape(B * V, 4, 4), self.cfg.grid)  # (B·V)×1×Z×Y×X
        return free.to(depth.dtype).reshape(B, V, 1, *self.cfg.grid.shape_zyx)  # B×V×1×Z×Y×X

    def _valid_pixels(self, depth: torch.Tensor, pix_T_cam: torch.Tensor, cam_T_ref: torch.Tensor,
                      size: tuple[int, int]) -> torch.Tensor:
        """Target pixels with a depth return whose point lies inside the grid, at the render size.

        depth: B×H×W, pix_T_cam, cam_T_ref: B×4×4 -> B×1×Hr×Wr float in {0, 1}.
        """
        B, H, W = depth.shape
        g = self.cfg.grid
        xyz_cam, valid = depth_to_points(depth, pix_T_cam)             # B×(H·W)×3, B×(H·W)
        xyz_ref = se3.apply(se3.invert(cam_T_ref), xyz_cam)            # B×(H·W)×3
        lo = torch.tensor(g.bounds_min, device=depth.device)
        hi = torch.tensor(g.bounds_max, device=depth.device)
        inside = valid & ((xyz_ref >= lo) & (xyz_ref < hi)).all(dim=-1)  # B×(H·W)
        mask = inside.to(depth.dtype).reshape(B, 1, H, W)              # B×1×H×W
        return (F.interpolate(mask, size=size, mode="nearest") > 0.5).to(depth.dtype)
