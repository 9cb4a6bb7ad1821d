"""Egomotion: coarse-to-fine 6-DoF alignment of two unregistered 3D input volumes (paper appendix).

Conventions (docs/conventions.md#poses): poses are 4×4 `a_T_b` (p_a = a_T_b @ p_b); volumes B×C×Z×Y×X on the
map grid. The REFERENCE volume lives in `ref0` (the map frame at t0), the QUERY volume in `ref1` (at t1); the
module estimates `ref0_T_ref1`. Warping the query into ref0 is `warp_rigid(query, ref1_T_ref0, grid)`.

Per scale s (coarse to fine, each an average-pooled copy of the module's OWN features):
1. candidates: the current estimate E (ref0_T_ref1) left-composed with each candidate rotation R_i about
   the ref0 origin, E_i = R_i · E;
2. the ORIGINAL pooled query features are warped ONCE by each composed candidate (inverse-compositional:
   never a warped volume again, so interpolation error does not accumulate);
3. a 3D cross-correlation cost volume against the reference over displacements within ±radius voxels,
   averaged over space (computed directly as that mean: core.models.cost_volume.mean_correlation_3d) -> one score per (rotation, displacement), standardised per example;
4. a 6-DoF update δ = (ω rad axis-angle, t metres) expressed in ref0, E ← exp(δ) · E, made of
   a) a soft-argmax over the scores (a correlator that works from the first step): with p = softmax(β·s)
      over all (rotation i, displacement d), ω = Σ p_i·(Euler offsets of R_i) (small angles, so Euler ≈
      axis-angle) and t = −voxel_s · Σ p_d·d. Why minus: a peak at d means warped(p + d) ≈ ref(p), i.e.
      the candidate E_i lands the query d voxels too far, so the truth is shift(−d)·R_i·E; exp(δ) =
      shift(t)·R(ω) composes in exactly that order. β (one per scale) is learned;
   b) plus a residual from a small MLP on the same scores, in units of the scale's search steps (its
      rotation outputs are multiplied by the candidate step per axis in radians, its translation
      outputs by the scale's voxel size). Why: Adam moves each weight by ~lr per step whatever the
      loss scale, so a head emitting radians directly jumped by degrees per step and added spurious
      rotation (measured on tiny: 2.4° vs the identity's 0.87° after 50 steps, translation fine).
The estimate entering a scale is detached (each scale is supervised on its own; the gradient does not
run back through the sampling coordinates into coarser scales). The last layer of every MLP starts at
zero, so an untrained module is the plain soft-argmax correlator; with `soft_argmax=False` it predicts
the identity. Measured on tiny held-out pairs (tests/benchmarks/bench_issue4_training.py): the MLP
alone, trained from identity, added spurious rotation (3.2° vs identity 0.87°) — the prior fixes the
scale and sign of the update, so the MLP only learns a small correction.

Sub-voxel stage (`refine`, core.models.egomotion_refine.FeatureMetricRefiner; None by default here and
in every bundle saved before it, on for new modules from core.tasks.egomotion): after the coarse scales,
a few Gauss-Newton iterations of dense alignment on the FULL grid of the input volumes' occupancy channel,
weighted per voxel by confidences learned from the encoder's features, differentiable (trained by the
pose loss on its output). It needs `input_occupancy="splat"` (continuous occupancy,
core.models.input_volume) to be worth it. Why (small preset, 8 moving-camera test pairs, true motion
0.012 rad / 0.81 m, tests/benchmarks/bench_egomotion_precision.py): trained 300 steps on binary occupancy,
the coarse scales end at R 0.0078 rad / t 0.23 m (2 m scale 0.010 / 0.19, 1 m scale no better); the
best hard choice of the 1 m scale's lattice from its entering estimate is 0.008 / 0.19 m, and binary
occupancy itself is a floor near ICP's error ×3: dense alignment of two binary volumes of the SAME points,
moved by the true motion, ends 0.0034 rad / 0.061 m off (splatted: 0.0005 / 0.005). With splatted input
and this stage: R 0.00125-0.00130 rad / t 0.024-0.027 m (seeds 0, 1 × 300 steps; 0, 2 × 100) against
point-to-plane ICP's 0.00107 / 0.026; on 32 fresh moving-camera pairs (seed 7, not used to tune the
stage) R 0.00185-0.00194 / t 0.039-0.043 against ICP's 0.00137 / 0.038 (README "Egomotion"). Cost:
≈ 30 ms per pair at small on one thread.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import check_shape
from core.geometry import se3
from core.geometry.grid import GridConfig
from core.geometry.resample import warp_rigid
from core.geometry.warp_many import warp_rigid_many
from core.models.cost_volume import displacements, mean_correlation_3d
from core.models.egomotion_fine import FineAlignment, FineFrame, align_fine, fine_grid
from core.models.egomotion_refine import FeatureMetricRefiner
from core.models.egomotion_rotations import candidate_angles, candidate_rotations
from core.models.encoder3d import Encoder3D
from core.models.input_volume import OCCUPANCY_KINDS
from core.precision import full_precision, geometry_dtype


def default_scales(grid: GridConfig) -> tuple[float, ...]:
    """Quarter and half resolution (full resolution costs 8× more for little gain on a 2-scale MLP), unless
    the grid is so thin along Y (the thinnest axis) that a quarter would leave fewer than 2 voxels."""
    return (0.25, 0.5) if grid.Y >= 8 else (0.5, 1.0)


def pool_to(vol: torch.Tensor, grid: GridConfig) -> torch.Tensor:
    """Average-pool B×C×Z×Y×X to the grid's counts (identity when they already match)."""
    if tuple(vol.shape[-3:]) == grid.shape_zyx:
        return vol
    return F.adaptive_avg_pool3d(vol, grid.shape_zyx)  # B×C×Zs×Ys×Xs


@full_precision
def se3_exp_update(delta: torch.Tensor) -> torch.Tensor:
    """δ: B×6 (axis-angle radians, translation metres) -> B×4×4 [exp(ω) | t]."""
    return se3.from_rt(se3.axis_angle_to_matrix(delta[:, :3]), delta[:, 3:])


# The fine stage of new modules and of bundles saved before the option (core.models.egomotion_fine has the
# numbers): point-to-TSDF on a grid 4× finer than the map's. A bundle that saved its stage keeps it.
DEFAULT_FINE_ALIGNMENT = {"kind": "tsdf", "factor": 4}


class EgomotionNet(nn.Module):
    """Two 4-channel input volumes (ref0 and ref1) -> `ref0_T_ref1` per scale."""

    def __init__(self, *, grid: GridConfig | dict, in_channels: int = 4, width: int = 8,
                 feature_dim: int = 16, scales: tuple[float, ...] | None = None,
                 rotation_steps_deg: tuple[tuple[float, float, float], ...] | None = None,
                 rotation_counts: tuple[int, int, int] = (3, 3, 3),
                 radius: tuple[int, int, int] = (2, 1, 2), hidden: int = 128, soft_argmax: bool = True,
                 temperature: float = 4.0, input_occupancy: str = "binary", refine: dict | None = None,
                 fine_alignment: dict | None = DEFAULT_FINE_ALIGNMENT) -> None:
        super().__init__()
        self.grid = grid if isinstance(grid, GridConfig) else GridConfig.from_dict(grid)
        self.scales = tuple(scales) if scales is not None else default_scales(self.grid)
        if len(self.scales) < 1:
            raise ValueError("EgomotionNet: need at least one scale")
        # Coarse scales look for larger rotations; yaw (about Y, down) gets twice the step of pitch/roll.
        if rotation_steps_deg is None:
            rotation_steps_deg = tuple((2.0 / 2 ** i, 4.0 / 2 ** i, 2.0 / 2 ** i) for i in range(len(self.scales)))
        if len(rotation_steps_deg) != len(self.scales):
            raise ValueError("EgomotionNet: one rotation step triple per scale")
        self.rotation_steps_deg = tuple(tuple(float(v) for v in s) for s in rotation_steps_deg)
        self.rotation_counts = tuple(int(n) for n in rotation_counts)
        self.radius = tuple(int(r) for r in radius)
        self.in_channels, self.width, self.feature_dim, self.hidden = in_channels, width, feature_dim, hidden
        self.soft_argmax, self.temperature = bool(soft_argmax), float(temperature)
        # β of the soft-argmax per scale, learned in log space (β > 0); scores are standardised, so β ≈ 4
        # puts most of the mass on the few best candidates of an untrained encoder.
        self.log_beta = nn.Parameter(torch.full((len(self.scales),), math.log(self.temperature)))
        self.encoder = Encoder3D(in_channels=in_channels, width=width, out_channels=feature_dim)
        n_rot = self.rotation_counts[0] * self.rotation_counts[1] * self.rotation_counts[2]
        n_disp = (2 * self.radius[0] + 1) * (2 * self.radius[1] + 1) * (2 * self.radius[2] + 1)
        self.heads = nn.ModuleList()
        for _ in self.scales:
            head = nn.Sequential(nn.Linear(n_rot * n_disp, hidden), nn.LeakyReLU(0.1),
                                 nn.Linear(hidden, hidden), nn.LeakyReLU(0.1), nn.Linear(hidden, 6))
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)
            self.heads.append(head)
        for i, steps in enumerate(self.rotation_steps_deg):
            self.register_buffer(f"candidates_{i}", candidate_rotations(steps, self.rotation_counts),
                                 persistent=False)
            self.register_buffer(f"candidate_angles_{i}", candidate_angles(steps, self.rotation_counts),
                                 persistent=False)
        self.register_buffer("displacements", displacements(self.radius), persistent=False)
        # Sub-voxel stage (core.models.egomotion_refine); None (the default, and every module saved before
        # it existed): the coarse scales' estimate is final. `input_occupancy` says which occupancy the
        # module's input volumes carry (core.models.egomotion_inputs.egomotion_input_volume builds them).
        if input_occupancy not in OCCUPANCY_KINDS:
            raise ValueError(f"EgomotionNet: input_occupancy must be one of {OCCUPANCY_KINDS}")
        self.input_occupancy = input_occupancy
        self.refiner = None if refine is None else FeatureMetricRefiner(feature_dim=feature_dim, **refine)
        # The last stage at inference (core.models.egomotion_fine): geometric alignment on a finer grid (frame
        # 1's points against frame 0's TSDF, or the frames' splats), from the sub-voxel stage's estimate; only
        # for a module that has that stage and reads splats (bundles saved before the option get the default).
        # Callers pass each frame's FineFrame (core.models.egomotion_inputs.egomotion_fine_frame) to `refine_fine`.
        self.fine = (FineAlignment(**fine_alignment) if fine_alignment is not None and self.refiner is not None
                     and input_occupancy == "splat" else None)

    def config(self) -> dict:
        return {"grid": self.grid.to_dict(), "in_channels": self.in_channels, "width": self.width,
                "feature_dim": self.feature_dim, "scales": list(self.scales),
                "rotation_steps_deg": [list(s) for s in self.rotation_steps_deg],
                "rotation_counts": list(self.rotation_counts), "radius": list(self.radius),
                "hidden": self.hidden, "soft_argmax": self.soft_argmax, "temperature": self.temperature,
                "input_occupancy": self.input_occupancy,
                "refine": None if self.refiner is None else self.refiner.config(),
                "fine_alignment": None if self.fine is None else self.fine.to_dict()}

    @property
    def fine_grid(self) -> GridConfig | None:
        """The grid of the fine stage's volumes (None: the module has no fine stage)."""
        return None if self.fine is None else fine_grid(self.grid, self.fine.factor)

    def refine_fine(self, ref0_T_ref1: torch.Tensor, reference_fine: FineFrame | None,
                    query_fine: FineFrame | None) -> torch.Tensor:
        """The fine stage on an estimate B×4×4 and the frames' FineFrames on `fine_grid`
        (core.models.egomotion_inputs.egomotion_fine_frame; frame 0's, frame 1's): the estimate it ends at,
        B×4×4; the estimate as it is in training mode, without a fine stage, or without the frames."""
        if self.fine is None or self.training or reference_fine is None or query_fine is None:
            return ref0_T_ref1
        return align_fine(ref0_T_ref1, reference_fine, query_fine, self.fine_grid, self.fine)  # wraps bare volumes

    def scale_grid(self, scale: float) -> GridConfig:
        return self.grid if scale == 1.0 else self.grid.scaled(scale)

    def warp_query(self, query: torch.Tensor, ref0_T_ref1: torch.Tensor, grid: GridConfig) -> torch.Tensor:
        """Warp the query volume (ref1) into ref0: query B×C×Z×Y×X, ref0_T_ref1 B×4×4 -> B×C×Z×Y×X; or one
        query 1×C×Z×Y×X under R estimates R×4×4 -> R×C×Z×Y×X (the candidates of a scale), through the 2D
        sampler of core.geometry.warp_many (1.8× faster than the 3D sampler there, equal up to ~1e-4)."""
        if query.shape[0] == 1 and ref0_T_ref1.shape[0] > 1 and grid.X >= 2:
            return warp_rigid_many(query, se3.invert(ref0_T_ref1), grid)
        return warp_rigid(query.expand(ref0_T_ref1.shape[0], *query.shape[1:]), se3.invert(ref0_T_ref1), grid)

    def scores(self, reference: torch.Tensor, query: torch.Tensor, estimate: torch.Tensor,
               candidates: torch.Tensor, grid: GridConfig) -> torch.Tensor:
        """Alignment score of every (candidate rotation, displacement) at one scale.

        reference, query: B×C×Zs×Ys×Xs (query = the ORIGINAL pooled ref1 features), estimate: B×4×4,
        candidates: R×4×4 -> B×(R·D) standardised scores.
        """
        B = reference.shape[0]
        composed = se3.compose(candidates.unsqueeze(0), estimate.unsqueeze(1))  # B×R×4×4: R_i · E
        # Each example's ONE query under its R candidates (no R copies of it).
        warped = torch.stack([self.warp_query(query[b:b + 1], composed[b], grid)
                              for b in range(B)])  # B×R×C×Zs×Ys×Xs
        # = cross_correlation_3d(reference, warped_r).mean over space, for every r, as one convolution
        s = mean_correlation_3d(reference, warped, self.radius)  # B×R×D
        s = s.reshape(B, -1)  # B×(R·D), rotation-major as the candidates × displacements
        return (s - s.mean(1, keepdim=True)) / (s.std(1, keepdim=True) + 1e-6)

    def update_units(self, index: int, grid: GridConfig) -> torch.Tensor:
        """Units of the residual head's outputs at one scale: 6 (rotation step rad per axis, voxel m ×3)."""
        steps = torch.tensor([math.radians(v) for v in self.rotation_steps_deg[index]])
        return torch.cat([steps, torch.full((3,), grid.voxel_size)]).to(self.log_beta.device)

    @full_precision  # soft-argmax over rotation angles and voxel displacements: float32 under autocast
    def prior_update(self, scores: torch.Tensor, index: int, grid: GridConfig) -> torch.Tensor:
        """Soft-argmax of one scale's scores B×(R·D) -> δ B×6 (ω rad, t metres in ref0); see module doc."""
        B = scores.shape[0]
        angles = getattr(self, f"candidate_angles_{index}").to(scores.dtype)  # R×3
        disp = self.displacements.to(scores.dtype)  # D×3 (x, y, z) voxels
        p = torch.softmax(self.log_beta[index].exp() * scores, dim=1).reshape(B, angles.shape[0], disp.shape[0])  # B×R×D
        omega = p.sum(2) @ angles  # B×3
        t = -(p.sum(1) @ disp) * grid.voxel_size  # B×3
        return torch.cat([omega, t], dim=1)

    def encode(self, volume: torch.Tensor) -> torch.Tensor:
        """One input volume B×Cin×Z×Y×X -> the module's own features B×F×Z×Y×X. Each example is encoded on
        its own (BatchNorm in eval mode), so a stream encodes each frame once and reuses its features as
        the next pair's reference (`align`)."""
        check_shape("input volume", volume, (None, self.in_channels, *self.grid.shape_zyx))
        return self.encoder(volume)

    def align(self, ref_feat: torch.Tensor, query_feat: torch.Tensor, reference_input: torch.Tensor | None = None,
              query_input: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The alignment of encoded volumes: ref_feat (ref0), query_feat (ref1) B×F×Z×Y×X -> `ref0_T_ref1`
        B×4×4 and `per_scale` S×B×4×4 (see the module doc); with the sub-voxel stage (which also reads the
        input volumes B×Cin×Z×Y×X the features were encoded from) also `refine_steps` K×B×4×4."""
        check_shape("ref_feat", ref_feat, (None, self.feature_dim, *self.grid.shape_zyx))
        check_shape("query_feat", query_feat, tuple(ref_feat.shape))
        B = ref_feat.shape[0]
        # Poses stay float32 when the features are bf16 (autocast): core.precision.
        pose_dtype = geometry_dtype(ref_feat.dtype)
        estimate = torch.eye(4, dtype=pose_dtype, device=ref_feat.device).expand(B, 4, 4)
        per_scale = []
        for i, (scale, head) in enumerate(zip(self.scales, self.heads)):
            grid_s = self.scale_grid(scale)
            ref_s, query_s = pool_to(ref_feat, grid_s), pool_to(query_feat, grid_s)
            candidates = getattr(self, f"candidates_{i}").to(pose_dtype)
            scores = self.scores(ref_s, query_s, estimate.detach(), candidates, grid_s)
            delta = head(scores) * self.update_units(i, grid_s).to(scores.dtype)  # B×6
            if self.soft_argmax:
                delta = delta + self.prior_update(scores, i, grid_s)
            estimate = se3.compose(se3_exp_update(delta), estimate.detach())  # B×4×4
            per_scale.append(estimate)
        out = {"ref0_T_ref1": estimate, "per_scale": torch.stack(per_scale, dim=0)}
        if self.refiner is not None:
            if reference_input is None or query_input is None:
                raise ValueError("EgomotionNet.align: this module refines on the input volumes; pass them")
            check_shape("reference_input", reference_input, (B, self.in_channels, *self.grid.shape_zyx))
            check_shape("query_input", query_input, tuple(reference_input.shape))
            refined, steps = self.refiner(reference_input, query_input, ref_feat, query_feat, estimate.detach(),
                                          self.grid)
            out.update(ref0_T_ref1=refined, refine_steps=torch.stack(steps, dim=0))
        return out

    def forward(self, reference_input: torch.Tensor, query_input: torch.Tensor) -> dict[str, torch.Tensor]:
        """reference_input (ref0), query_input (ref1): B×Cin×Z×Y×X input volumes.

        Returns `ref0_T_ref1` B×4×4 (final) and `per_scale` S×B×4×4 (estimate after each scale); with the
        sub-voxel stage also `refine_steps` K×B×4×4 (after each of its iterations; the last is final).
        """
        check_shape("reference_input", reference_input, (None, self.in_channels, *self.grid.shape_zyx))
        check_shape("query_input", query_input, tuple(reference_input.shape))
        B = reference_input.shape[0]
        feats = self.encoder(torch.cat([reference_input, query_input], dim=0))  # 2B×F×Z×Y×X (one batch: training)
        return self.align(feats[:B], feats[B:], reference_input, query_input)


def pose_loss(est_T: torch.Tensor, gt_T: torch.Tensor, *, rotation_weight: float = 10.0) -> dict[str, torch.Tensor]:
    """Supervised egomotion loss on `ref0_T_ref1` (both B×4×4, frame ref0).

    rotation: chordal ‖R_est − R_gt‖_F / √2 (= 2·sin(θ/2)·… ≈ θ radians for small θ, with a smooth
    gradient at 0 unlike acos); translation: ‖t_est − t_gt‖₁ metres in ref0. Returns `loss` =
    rotation_weight·rotation + translation and both parts (means over B).
    """
    R_e, t_e = se3.split_rt(est_T)
    R_g, t_g = se3.split_rt(gt_T)
    rot = (R_e - R_g).flatten(1).norm(dim=1) / (2.0 ** 0.5)
    trans = (t_e - t_g).abs().sum(dim=1)
    return {"loss": rotation_weight * rot.mean() + trans.mean(), "rotation": rot.mean(), "translation": trans.mean()}
