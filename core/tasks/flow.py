"""3D imagination flow training step over frozen mapper features (paper §3.3 and appendix).

Per step, at a random t with t+1 available, the pair the flow module compares (`inputs`, see
core.models.flow3d for why "volume" exists):
  "features": F0 = map of time t in ref_t; F1 = map of time t+1 lifted straight into ref_t with the
  record poses (egomotion-stabilised by re-unprojection, no resampling). The mapper is frozen (no
  gradient, eval mode): the paper trains flow over frozen features, and the warp loss would otherwise
  collapse them. Measured on tiny: these maps do not carry object motion (flow over them ties zero motion);
  "volume": the 4-channel fused input volumes (occupancy + RGB) of t and t+1, lifted the same way; the
  mapper is not run. Below, F0/F1 stand for whichever pair.
Losses:
  synthetic  — F0 moved by a random rigid motion (equal thirds large ±6°/±1 m, small ±1°/±0.1 m, zero;
               core.models.flow_synthetic); L1 between predicted and true flow at every level
               (true flow average-pooled to the level), finest level weight 1, each coarser half;
               with probability `object_fraction` per step the motion instead moves one random block
               of F0 (object-sized, core.models.flow_synthetic.sample_object_motions) and leaves the
               rest static — still self-supervised, at the scale of the objects real pairs contain; the
               place it left is empty for input volumes (as in a real pair) and keeps the old content
               for feature maps (the background it hid);
               with probability `reproject_fraction` a rigid step's moved input is frame t itself
               re-unprojected with the motion (its depth points lifted with cam_T_ref·M⁻¹, motions from
               REPROJECT_RANGES: large, small and a jitter at the egomotion module's error scale) instead
               of F0 resampled: a pose error re-voxelises the scene, which resampling never shows the module;
  warp       — mean over the OCCUPIED voxels of t (any view's depth point in the voxel; self-supervised)
               of Σ_c |F0 − warp_flow(F1, flow(F0, F1))| (3D feature constancy). Why occupied only: free
               space carries no motion evidence, and averaging over all voxels (tiny: ~15% occupied,
               ~1% moving) diluted the real-motion signal below the smoothness term (measured: the flow
               learned the synthetic motions but predicted ~0 on real pairs);
  smooth     — mean |∇flow| of the real-pair flow (forward differences along x, y, z).
loss = synthetic + warp_weight·warp + smooth_weight·smooth.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from core.errors import ShapeError
from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_flow, warp_rigid
from core.models.flow3d import FLOW_INPUTS, VOLUME_CHANNELS, Flow3D, downsample_flow
from core.models.flow_synthetic import (
    REPROJECT_RANGES, move_block, rigid_flow, sample_motions, sample_object_motions,
)
from core.models.egomotion_inputs import fused_input_volume
from core.models.latent_map import Mapper
from core.presets import Preset
from core.tasks.frozen_maps import FrozenMapCache
from core.tasks.poses import cam_T_ref
from core.tasks.view_subset import random_view_subset


@dataclass(frozen=True)
class FlowTaskConfig:
    grid: GridConfig
    feature_dim: int = 32
    encoder_width: int = 64
    encoder_full_res: int = 0       # Encoder3D.full_res (see core.models.encoder3d)
    channels: int = 16
    levels: int = 3
    radius: tuple[int, int, int] = (1, 1, 1)  # Flow3D.radius: cost-volume window (x, y, z) at every level
    # Flow3D.refine_radius: the grid step's window (None: radius) and Flow3D.refine_aggregate: the box its costs
    # are averaged over (±x, y, z). Default ±3/±1/±3 with ±1 boxes, the benchmark's feature-flow recipe (its
    # `--task-options`). Why (session 36): the small report's input-volume flows, trained with a ±1 grid step, recovered
    # 0.09 of the motion of objects moving > 2.5 voxels a step (tests/benchmarks/bench_flow_magnitude.py); the same
    # trained modules with this window at inference (the step has no weights that depend on it) went from
    # AP3D@0.5 0.30 / 0.35 / 0.41 to 0.93 / 0.89 / 0.85 (static camera) and 0.27 / 0.30 / 0.41 to 0.84 / 0.82 /
    # 0.80 (moving camera, with the egomotion module), seeds 0 / 1 / 2, on 32 held-out records of data seed 7.
    # Its cost: the module's forward at small, one thread, 120 → 279 ms (the stream's speed: README).
    refine_radius: tuple[int, int, int] | None = (3, 1, 3)
    cost_channels: int = 0          # Flow3D.cost_channels: 1×1×1 squeeze of the window costs (0: none)
    refine_aggregate: tuple[int, int, int] = (1, 1, 1)
    warp_weight: float = 1.0
    smooth_weight: float = 0.05
    finest: int = 1                 # Flow3D.finest: 1 = PWC's half-resolution last decoder, 0 = on the grid
    refine: bool = True             # Flow3D.refine: soft-argmax correlator step on the grid after finest=1
    beta: float = 30.0              # Flow3D.beta: initial soft-argmax sharpness (see core.models.flow3d)
    zero_bias: float = 0.05         # Flow3D.zero_bias: initial cosine bonus of zero motion in the refinement
    occupied_warp: bool = True      # warp loss over occupied voxels of t only (see module doc)
    object_fraction: float = 0.5    # share of steps whose synthetic motion moves one block (see module doc)
    # Share of the rigid synthetic steps whose moved input is re-unprojected (see module doc). 0 (default):
    # none. Why: with exact poses a static camera's static content re-voxelises identically, but a pose a
    # few mm / 0.2 mrad off re-voxelises it differently and the module then reports metres-per-second motion
    # in places (README, "Which voxels move"): it only ever saw resampled or identical inputs.
    reproject_fraction: float = 0.0
    # Flow3D.inputs: "volume" (default: the fused occupancy+RGB input volumes) or "features" (mapper maps,
    # the paper's choice). Measured on tiny (bench_issue4_training.py, 150 steps): flow over the maps ties
    # zero motion on moving voxels (1.177 vs 1.156 L1 voxels); over the input volumes it beats it (0.872).
    inputs: str = "volume"
    unit_cost: bool = True          # Flow3D.unit_cost: cosine cost volume
    soft_argmax: bool = False       # Flow3D.soft_argmax: correlator prior at every decoder level too
    seed: int | None = None
    # Each step trains on a random subset of at least this many of the record's views (core.tasks.view_subset);
    # None (default): every view. Measured at 1 in session 6: no gain on single-view pairs (see that module).
    min_views: int | None = None
    # MiB of each training example's flow inputs (both maps or volumes, and the occupied voxels) kept across
    # steps of one training call (core.tasks.frozen_maps; 0 = none). Why: with every view the inputs of a record
    # are the same at every epoch, and the frozen mapper's two forwards were ~10 % of a flow-over-features step
    # (small preset, the bench's recipe, one thread). One small-preset record's pair over features is 8.25 MiB,
    # so 1024 holds ~120 records (the small plan has 64); a cache that mostly misses turns itself off.
    frozen_input_cache_mb: int = 1024

    def __post_init__(self) -> None:
        if self.frozen_input_cache_mb < 0:
            raise ValueError(f"frozen_input_cache_mb must be >= 0 MiB, got {self.frozen_input_cache_mb}")


def smoothness(flow: torch.Tensor) -> torch.Tensor:
    """flow B×3×Z×Y×X -> mean absolute forward difference over the three axes (scalar)."""
    dz = (flow[:, :, 1:] - flow[:, :, :-1]).abs().mean()
    dy = (flow[:, :, :, 1:] - flow[:, :, :, :-1]).abs().mean()
    dx = (flow[..., 1:] - flow[..., :-1]).abs().mean()
    return (dx + dy + dz) / 3.0


def multilevel_l1(levels: list[torch.Tensor], gt: torch.Tensor) -> torch.Tensor:
    """Per-level flows (coarse first) vs full-res gt B×3×Z×Y×X: Σ_l w_l · mean L1 (w = 1 finest, ½ per level up)."""
    total = gt.new_zeros(())
    n = len(levels)
    for i, flow in enumerate(levels):
        target = downsample_flow(gt, tuple(flow.shape[-3:]))
        total = total + 0.5 ** (n - 1 - i) * (flow - target).abs().sum(1).mean()
    return total


class FlowTask(nn.Module):
    def __init__(self, *, config: FlowTaskConfig) -> None:
        super().__init__()
        self.cfg = config
        self.mapper = Mapper(grid=config.grid, width=config.encoder_width, feature_dim=config.feature_dim,
                             full_res=config.encoder_full_res)
        self.mapper.requires_grad_(False)
        if config.inputs not in FLOW_INPUTS:
            raise ValueError(f"FlowTaskConfig.inputs must be one of {FLOW_INPUTS}, got {config.inputs!r}")
        in_channels = config.feature_dim if config.inputs == "features" else VOLUME_CHANNELS
        self.flow = Flow3D(in_channels=in_channels, channels=config.channels, levels=config.levels,
                           radius=tuple(config.radius),
                           finest=config.finest, inputs=config.inputs, unit_cost=config.unit_cost,
                           soft_argmax=config.soft_argmax, refine=config.refine, beta=config.beta,
                           zero_bias=config.zero_bias, cost_channels=config.cost_channels,
                           refine_radius=config.refine_radius, refine_aggregate=config.refine_aggregate)
        self._generator = torch.Generator().manual_seed(config.seed) if config.seed is not None else None
        self.frozen_inputs = (FrozenMapCache(max_bytes=config.frozen_input_cache_mb << 20)
                              if config.frozen_input_cache_mb > 0 else None)

    @staticmethod
    def from_preset(preset: Preset, **overrides) -> "FlowTask":
        base = dict(grid=preset.grid, feature_dim=preset.feature_dim, encoder_width=preset.encoder_width,
                    encoder_full_res=preset.encoder_full_res)
        base.update(overrides)
        return FlowTask(config=FlowTaskConfig(**base))

    def exported_modules(self) -> dict[str, nn.Module]:
        return {"mapper": self.mapper, "flow": self.flow}

    def train(self, mode: bool = True) -> "FlowTask":
        super().train(mode)
        self.mapper.eval()  # frozen features: BatchNorm keeps the loaded statistics
        return self

    @torch.no_grad()
    def flow_inputs(self, batch: dict[str, torch.Tensor], t: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What the flow module compares, t and t+1 in ref_t (B×C×Z×Y×X each, C = flow.in_channels), and
        the occupied voxels of t (B×1×Z×Y×X). In training, from the cache of each example's inputs when it has
        them (`FlowTaskConfig.frozen_input_cache_mb`)."""
        rgb, depth = batch["rgb"], batch["depth"]
        views = [rgb[:, t], depth[:, t], rgb[:, t + 1], depth[:, t + 1], batch["pix_T_cam"],
                 cam_T_ref(batch, t, t), cam_T_ref(batch, t + 1, t)]   # B×V×…, the pair's views, poses in ref_t
        if self.training and self.frozen_inputs is not None and self.frozen_inputs.enabled:
            return self.frozen_inputs.outputs(self.mapper, self._pair_inputs, views)
        return self._pair_inputs(views)

    def _pair_inputs(self, views: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rgb_t, depth_t, rgb_t1, depth_t1, pix_T_cam, cam_t_T_ref, cam_t1_T_ref), each B×V×… -> flow_inputs'."""
        rgb0, depth0, rgb1, depth1, pix, cam0, cam1 = views
        v0 = fused_input_volume(rgb0, depth0, pix, cam0, self.cfg.grid)  # B×4×Z×Y×X
        occupied = (v0[:, :1] > 0).to(v0.dtype)                          # B×1×Z×Y×X
        if self.cfg.inputs == "volume":  # the frozen mapper is not needed for training
            return v0, fused_input_volume(rgb1, depth1, pix, cam1, self.cfg.grid), occupied
        return self.mapper(rgb0, depth0, pix, cam0), self.mapper(rgb1, depth1, pix, cam1), occupied

    @torch.no_grad()
    def reprojected_input(self, batch: dict[str, torch.Tensor], t: int, motion: torch.Tensor) -> torch.Tensor:
        """What the flow module compares for frame t after the scene moved by `motion` (B×4×4, in ref_t):
        frame t's views lifted with cam_T_ref·motion⁻¹, so each depth point lands at motion·p, re-voxelised
        as a real pose change would be. -> B×C×Z×Y×X (C = flow.in_channels)."""
        rgb, depth, pix = batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"]
        cam = cam_T_ref(batch, t, t) @ se3.invert(motion)[:, None]  # B×V×4×4
        if self.cfg.inputs == "volume":
            return fused_input_volume(rgb, depth, pix, cam, self.cfg.grid)  # B×4×Z×Y×X
        return self.mapper(rgb, depth, pix, cam)  # B×F×Z×Y×X

    @torch.no_grad()
    def occupied(self, batch: dict[str, torch.Tensor], t: int) -> torch.Tensor:
        """Voxels of ref_t holding a depth point of any view at t: B×1×Z×Y×X float in {0, 1}."""
        vol = fused_input_volume(batch["rgb"][:, t], batch["depth"][:, t], batch["pix_T_cam"],
                                 cam_T_ref(batch, t, t), self.cfg.grid)  # B×4×Z×Y×X
        return (vol[:, :1] > 0).to(vol.dtype)

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        B, T = batch["rgb"].shape[:2]
        if T < 2:
            raise ShapeError(f"flow training needs records with at least 2 time steps, got T={T}")
        t = int(torch.randint(T - 1, (1,), generator=self._generator))
        if self.cfg.min_views is not None:
            batch = random_view_subset(batch, min_views=self.cfg.min_views, generator=self._generator)
        f0, f1, occupied = self.flow_inputs(batch, t)
        g = self.cfg.grid
        if float(torch.rand((), generator=self._generator)) < self.cfg.object_fraction:
            motion, block = sample_object_motions(B, g, generator=self._generator, dtype=f0.dtype, device=f0.device)
            # only the block moved; input volumes leave empty space behind it (as a real pair's do), feature
            # maps the old content (standing in for the background the object occluded)
            moved, gt = move_block(f0, motion, block, g, vacate=self.cfg.inputs == "volume")
        elif (self.cfg.reproject_fraction > 0
              and float(torch.rand((), generator=self._generator)) < self.cfg.reproject_fraction):
            motion, _ = sample_motions(B, generator=self._generator, dtype=f0.dtype, device=f0.device,
                                       ranges=REPROJECT_RANGES)
            moved = self.reprojected_input(batch, t, motion)  # B×C×Z×Y×X: frame t lifted after the scene moved
            gt = rigid_flow(motion, g)
        else:
            motion, _ = sample_motions(B, generator=self._generator, dtype=f0.dtype, device=f0.device)
            moved = warp_rigid(f0, se3.invert(motion), g)  # B×F×Z×Y×X: f0 after the scene moved by `motion`
            gt = rigid_flow(motion, g)
        synth = self.flow(f0, moved)
        loss_synth = multilevel_l1(synth["levels"], gt)
        real = self.flow(f0, f1)
        residual = (f0 - warp_flow(f1, real["flow"])).abs().sum(1, keepdim=True)  # B×1×Z×Y×X
        if self.cfg.occupied_warp:
            loss_warp = (residual * occupied).sum() / occupied.sum().clamp_min(1.0)
        else:
            loss_warp = residual.mean()
        loss_smooth = smoothness(real["flow"])
        loss = loss_synth + self.cfg.warp_weight * loss_warp + self.cfg.smooth_weight * loss_smooth
        synth_epe = (synth["flow"].detach() - gt).norm(dim=1).mean()
        return {"loss": loss, "loss_synth": loss_synth.detach(), "loss_warp": loss_warp.detach(),
                "loss_smooth": loss_smooth.detach(), "synth_epe": synth_epe,
                "real_flow_mag": real["flow"].detach().norm(dim=1).mean()}
