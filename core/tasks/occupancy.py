"""Occupancy training step: the occupancy head (and, unless frozen, the mapper) from depth labels.

Paper protocol: the map is built from `input_views` views (default 1, a random one) and the labels are
the union of that input's own labels and one other random view's (occupied = voxelised points, free =
ray traversal; everything else unlabelled), so the head must also fill in space the input did not see.
The loss is the class-balanced logistic loss (core.losses.occupancy). `--freeze-features` (the
training machinery freezing `mapper`) trains the head alone on fixed features.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from core.errors import ShapeError
from core.eval.occupancy_metrics import occupancy_counts, occupancy_scores
from core.geometry.grid import GridConfig
from core.losses.occupancy import balanced_occupancy_loss
from core.models.latent_map import Mapper, masked_average
from core.models.occupancy_head import OccupancyHead
from core.presets import Preset
from core.tasks.occupancy_labels import occupancy_labels
from core.tasks.poses import cam_T_ref


@dataclass(frozen=True)
class OccupancyTaskConfig:
    grid: GridConfig
    feature_dim: int = 32
    encoder_width: int = 64
    encoder_full_res: int = 0       # Encoder3D.full_res (see core.models.encoder3d)
    input_views: int = 1
    seed: int | None = None


def choose_views(V: int, input_views: int, generator: torch.Generator | None) -> tuple[list[int], list[int]]:
    """Random input views and label views (inputs + one other view when V allows)."""
    perm = torch.randperm(V, generator=generator).tolist()
    k = max(1, min(input_views, V))
    inputs = perm[:k]
    labels = perm[:k + 1] if V > k else perm[:k]
    return sorted(inputs), sorted(labels)


class OccupancyTask(nn.Module):
    def __init__(self, *, config: OccupancyTaskConfig) -> None:
        super().__init__()
        self.cfg = config
        self.mapper = Mapper(grid=config.grid, width=config.encoder_width, feature_dim=config.feature_dim,
                             full_res=config.encoder_full_res)
        self.occupancy = OccupancyHead(in_channels=config.feature_dim)
        self._generator = torch.Generator().manual_seed(config.seed) if config.seed is not None else None

    @staticmethod
    def from_preset(preset: Preset, **overrides) -> "OccupancyTask":
        base = dict(grid=preset.grid, feature_dim=preset.feature_dim, encoder_width=preset.encoder_width,
                    encoder_full_res=preset.encoder_full_res)
        base.update(overrides)
        return OccupancyTask(config=OccupancyTaskConfig(**base))

    def exported_modules(self) -> dict[str, nn.Module]:
        return {"mapper": self.mapper, "occupancy": self.occupancy}

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        rgb = batch["rgb"]  # B×T×V×3×H×W
        B, T, V = rgb.shape[:3]
        if V < 1:
            raise ShapeError("occupancy training needs at least one view")
        t = int(torch.randint(T, (1,), generator=self._generator))
        inputs, label_views = choose_views(V, self.cfg.input_views, self._generator)
        cam = cam_T_ref(batch, t, t)  # B×V×4×4
        depth, pix = batch["depth"][:, t], batch["pix_T_cam"]
        feats, in_view, _ = self.mapper.encode_views(rgb[:, t][:, inputs], depth[:, inputs], pix[:, inputs],
                                                     cam[:, inputs])
        features = masked_average(feats, in_view)  # B×F×Z×Y×X
        logits = self.occupancy(features)  # B×1×Z×Y×X
        occupied, free = occupancy_labels(depth[:, label_views], pix[:, label_views], cam[:, label_views],
                                          self.cfg.grid)
        loss = balanced_occupancy_loss(logits, occupied, free)
        scores = occupancy_scores(occupancy_counts(torch.sigmoid(logits.detach()), occupied, free))
        # A class with no labels in this batch gives NaN; the training loop stops on any non-finite value
        # and every rank must report the same keys, so an undefined score is reported as 0.
        metrics = {k: torch.tensor(float(scores[k])).nan_to_num(0.0)
                   for k in ("acc_occupied", "acc_free", "acc_all", "iou_occupied")}
        return {"loss": loss, **metrics}
