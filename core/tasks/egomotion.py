"""Egomotion training step: supervised `ref0_T_ref1` from record poses.

Target and frame, explicitly: the module estimates ref0_T_ref1 = inv(world_T_ref[t0]) · world_T_ref[t1]
(maps points of ref_t1 into ref_t0; its translation is in metres in ref_t0). The loss is
`core.models.egomotion.pose_loss` (chordal rotation ≈ angle in rad, weighted; L1 translation in m),
summed over the module's scales (deep supervision of every coarse-to-fine step) and, with the sub-voxel
stage (`refine`), its refined estimate (the gradient runs through its Gauss-Newton solves into the
features and confidences it aligns; the estimate it starts from is detached, as between scales).

The module is built with splatted input occupancy and the sub-voxel Gauss-Newton stage
(`input_occupancy="splat"`, `refine=True`, core.models.egomotion doc): measured at small, 7-9 × ICP's
errors without them, 0.95-1.21 × with them (docs/findings.md, "Egomotion is on par with ICP"). `refine=False, input_occupancy="binary"`
builds the module as before.

Augmentation (on by default; needed when the data's camera does not move): the query frame is lifted
into a randomly perturbed map frame ref1' (ref1_T_ref1' = yaw ±`augment_deg`, pitch and roll
±`augment_deg`/3, x and z ±`augment_m`, y ±`augment_m`/4), by re-unprojecting the views with
cam_T_ref1' = cam_T_ref1 · ref1_T_ref1' (exact, no resampling); the target becomes
ref0_T_ref1 · ref1_T_ref1'. Records with T = 1 pair a frame with its perturbed self.
As the flow's synthetic motions, the perturbation is drawn per example in equal thirds: large (the
ranges above), small (a sixth of them) and none (the recorded motion as it is). Why: trained on large
perturbations only, the module never sees the small rotations of real driving (|yaw| ≲ 2° per step)
and its error there stays at its large-motion error (measured: 3.2° vs the identity's 0.87°).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from core.geometry import se3
from core.geometry.grid import GridConfig
from core.eval.egomotion_metrics import relative_pose_errors
from core.models.egomotion import EgomotionNet, default_scales, pose_loss
from core.models.egomotion_inputs import egomotion_input_volume
from core.presets import Preset
from core.tasks.poses import cam_T_ref, ref0_T_ref1
from core.tasks.view_subset import random_view_subset


@dataclass(frozen=True)
class EgomotionTaskConfig:
    grid: GridConfig
    width: int = 8                  # encoder width of the module's own 3D encoder-decoder
    feature_dim: int = 8            # its feature channels
    scales: tuple[float, ...] | None = None  # None: core.models.egomotion.default_scales(grid)
    augment: bool = True
    augment_deg: float = 6.0
    augment_m: float = 1.0
    augment_mixture: bool = True    # equal thirds large / small / no perturbation (see module doc)
    radius: tuple[int, int, int] = (2, 1, 2)  # cross-correlation search radius (x, y, z) voxels per scale
    rotation_weight: float = 10.0
    seed: int | None = None
    # Each step trains on a random subset of at least this many of the record's views (core.tasks.view_subset);
    # None (default): every view. Measured at 1 in session 6: no gain on single-view pairs (see that module).
    min_views: int | None = None
    input_occupancy: str = "splat"  # continuous occupancy (core.models.input_volume); "binary": before
    refine: bool = True             # the sub-voxel Gauss-Newton stage (core.models.egomotion_refine)
    refine_learned_channels: int = 0  # learned feature channels of that stage (measured: no gain, 4 cost ~60 ms)


AUGMENT_SCALES = (1.0, 1.0 / 6.0, 0.0)  # large, small, none: drawn in equal thirds


def random_perturbation(B: int, *, max_deg: float, max_m: float, generator: torch.Generator | None,
                        dtype=torch.float32, device=None, mixture: bool = False) -> torch.Tensor:
    """Yaw-heavy random rigid transforms B×4×4 (see module doc for the ranges). `mixture`: scale each
    example's ranges by one of AUGMENT_SCALES, chosen uniformly."""
    u = torch.rand(B, 6, generator=generator, dtype=torch.float64) * 2.0 - 1.0  # B×6
    if mixture:
        pick = torch.randint(len(AUGMENT_SCALES), (B,), generator=generator)
        u = u * torch.tensor(AUGMENT_SCALES, dtype=torch.float64)[pick, None]
    rad = math.radians(max_deg)
    R = se3.euler_to_matrix(u[:, 0] * rad / 3, u[:, 1] * rad, u[:, 2] * rad / 3)  # B×3×3
    t = u[:, 3:] * torch.tensor([max_m, max_m / 4, max_m], dtype=torch.float64)  # B×3
    return se3.from_rt(R, t).to(dtype=dtype, device=device)


class EgomotionTask(nn.Module):
    def __init__(self, *, config: EgomotionTaskConfig) -> None:
        super().__init__()
        self.cfg = config
        self.egomotion = EgomotionNet(grid=config.grid, width=config.width, feature_dim=config.feature_dim,
                                      scales=config.scales or default_scales(config.grid),
                                      radius=tuple(config.radius), input_occupancy=config.input_occupancy,
                                      refine={"learned_channels": config.refine_learned_channels}
                                      if config.refine else None)
        self._generator = torch.Generator().manual_seed(config.seed) if config.seed is not None else None

    @staticmethod
    def from_preset(preset: Preset, **overrides) -> "EgomotionTask":
        base = dict(grid=preset.grid, width=max(8, preset.encoder_width // 2), feature_dim=preset.feature_dim)
        base.update(overrides)
        for key in ("scales", "radius"):
            if base.get(key) is not None:
                base[key] = tuple(base[key])
        return EgomotionTask(config=EgomotionTaskConfig(**base))

    def exported_modules(self) -> dict[str, nn.Module]:
        return {"egomotion": self.egomotion}

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        if self.cfg.min_views is not None:
            batch = random_view_subset(batch, min_views=self.cfg.min_views, generator=self._generator)
        rgb, depth, pix = batch["rgb"], batch["depth"], batch["pix_T_cam"]  # B×T×V×3×H×W, B×T×V×H×W, B×V×4×4
        B, T = rgb.shape[:2]
        t0 = int(torch.randint(max(T - 1, 1), (1,), generator=self._generator))
        t1 = min(t0 + 1, T - 1)
        cam0, cam1 = cam_T_ref(batch, t0, t0), cam_T_ref(batch, t1, t1)  # B×V×4×4
        target = ref0_T_ref1(batch, t0, t1)  # B×4×4
        if self.cfg.augment:
            P = random_perturbation(B, max_deg=self.cfg.augment_deg, max_m=self.cfg.augment_m,
                                    generator=self._generator, dtype=target.dtype, device=target.device,
                                    mixture=self.cfg.augment_mixture)
            cam1 = se3.compose(cam1, P[:, None])  # B×V×4×4: cam_T_ref1' = cam_T_ref1 · ref1_T_ref1'
            target = se3.compose(target, P)
        with torch.no_grad():
            vol0 = egomotion_input_volume(self.egomotion, rgb[:, t0], depth[:, t0], pix, cam0)  # B×4×Z×Y×X
            vol1 = egomotion_input_volume(self.egomotion, rgb[:, t1], depth[:, t1], pix, cam1)
        out = self.egomotion(vol0, vol1)
        stages = list(out["per_scale"]) + ([out["ref0_T_ref1"]] if "refine_steps" in out else [])
        losses = [pose_loss(est, target, rotation_weight=self.cfg.rotation_weight) for est in stages]
        loss = torch.stack([l["loss"] for l in losses]).sum()
        err = relative_pose_errors(out["ref0_T_ref1"].detach(), target)
        ident = relative_pose_errors(torch.eye(4, device=target.device).expand(B, 4, 4), target)
        return {"loss": loss, "loss_rotation": losses[-1]["rotation"].detach(),
                "loss_translation": losses[-1]["translation"].detach(),
                "rot_err_deg": err["rot_err_deg"].mean().float(), "trans_err_m": err["trans_err_m"].mean().float(),
                "identity_rot_err_deg": ident["rot_err_deg"].mean().float(),
                "identity_trans_err_m": ident["trans_err_m"].mean().float()}
