"""3D object detection step: the latent map of one time step -> Faster-RCNN-style anchor losses.

One step, at a random time step t of each record (B×T×V views):
  1. the latent map in ref_t from all V views with their known poses (core.models.latent_map.Mapper,
     the same map the pretraining step fuses) — under no_grad and in eval mode when the features are
     frozen (the paper freezes pretrained features and trains only the detector), then in training each
     example's map computed alone and kept for the epochs after (core.tasks.frozen_maps);
  2. ground truth: the record's boxes (world) moved to ref_t (transform_boxes with inv(world_T_ref[t])),
     the valid ones whose centre lies inside the grid, replaced by their axis-aligned bounding boxes
     (the paper's detector is axis-aligned; so is its evaluation of these boxes);
  3. anchors matched by bird's-eye-view IoU (≥ positive_iou positive, < negative_iou negative, plus
     each box's best anchor), `num_samples` anchors per example with ≤ half positives
     (core.models.detector_targets); binary cross-entropy on their objectness, smooth-L1 on the
     positives' deltas (normalised by the sample size, as torchvision's RPN).

Label budget (`labels=N`): only records with dataset index < N carry box labels; the batch must then
hold `record_index` (B int64, each record's index in its dataset) and the other records contribute no
detection loss (they are masked out of both terms; a batch without labelled records has loss 0).

Threshold choice: anchors sit every ~1 m (stride·voxel); a car-sized box offset by half a cell on both
axes from a same-sized anchor has BEV IoU ≈ 0.46, so positive ≥ 0.45 / negative < 0.3 gives each car a few
positives at every preset (measured on tiny synthetic records: ≈ 5 positive anchors per car, the
`num_pos` / `num_gt` metrics).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from core.errors import DataError
from core.geometry import se3
from core.geometry.boxes import transform_boxes
from core.geometry.grid import GridConfig
from core.models.detector3d import CAR_ANCHOR_SIZES, Detector3D
from core.models.detector_boxes import boxes_to_aabb, encode_deltas
from core.models.detector_targets import assign_anchors, sample_anchors
from core.models.latent_map import Mapper
from core.presets import Preset
from core.tasks.frozen_maps import FrozenMapCache
from core.tasks.poses import cam_T_ref

ANCHOR_SPACING_M = 1.0   # target spacing of anchor cells; stride = voxels per cell
CAR_HALF_HEIGHT_M = 0.825


@dataclass(frozen=True)
class DetectorTaskConfig:
    """Everything the detection step needs besides the batch (built from a preset by `from_preset`)."""

    grid: GridConfig
    feature_dim: int = 32                 # F of the map
    encoder_width: int = 64               # mapper's 3D encoder width (must match a pretrained mapper)
    encoder_full_res: int = 0             # mapper's full-resolution branch (must match too)
    width: int = 64                       # C of the detector's 3D neck
    head_width: int = 128                 # H of the bird's-eye-view head
    stride: int = 4                       # voxels per anchor cell
    anchor_sizes: tuple = CAR_ANCHOR_SIZES
    anchor_y: float = 1.175               # anchor centre height in ref (ground_y − half a car)
    positive_iou: float = 0.45
    negative_iou: float = 0.3
    num_samples: int = 256                # anchors per example per step
    positive_fraction: float = 0.5
    box_weight: float = 1.0
    smooth_l1_beta: float = 1.0 / 9.0
    labels: int | None = None             # label budget: records with index < labels carry boxes
    freeze_features: bool = True
    # Frozen features: MiB of latent maps kept across training steps (core.tasks.frozen_maps; 0 = none).
    # Why: the same record's map recurs every epoch, and the mapper's forward is ~40 % of a frozen step.
    frozen_map_cache_mb: int = 1024
    seed: int | None = None               # time-step choice / anchor sampling RNG

    def __post_init__(self) -> None:
        if not 0.0 <= self.negative_iou <= self.positive_iou <= 1.0:
            raise ValueError(f"need 0 ≤ negative_iou ≤ positive_iou ≤ 1, got {self.negative_iou}, "
                             f"{self.positive_iou}")
        if self.frozen_map_cache_mb < 0:
            raise ValueError(f"frozen_map_cache_mb must be >= 0 MiB, got {self.frozen_map_cache_mb}")
        if self.labels is not None and self.labels < 0:
            raise ValueError(f"labels must be ≥ 0 (a number of records), got {self.labels}")


def default_stride(grid: GridConfig) -> int:
    """Voxels per anchor cell: about ANCHOR_SPACING_M metres, and dividing every grid count."""
    stride = max(1, round(ANCHOR_SPACING_M / grid.voxel_size))
    while stride > 1 and any(n % stride for n in grid.shape_zyx):
        stride -= 1
    return stride


def gt_boxes_ref(batch: dict[str, torch.Tensor], t: int, grid: GridConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Ground-truth boxes of time t in ref_t: batch boxes B×T×K×7 (world), box_valid B×T×K,
    world_T_ref B×T×4×4 -> (boxes_ref B×K×7 canonical, keep B×K bool: valid and centre inside the grid)."""
    if "boxes" not in batch or "box_valid" not in batch:
        raise DataError("detector: the batch has no 'boxes'/'box_valid' (records without box labels)")
    boxes_world, valid = batch["boxes"][:, t], batch["box_valid"][:, t]    # B×K×7, B×K
    ref_T_world = se3.invert(batch["world_T_ref"][:, t])                    # B×4×4
    boxes_ref = transform_boxes(ref_T_world, boxes_world)                  # B×K×7
    lo = torch.tensor(grid.bounds_min, device=boxes_ref.device)
    hi = torch.tensor(grid.bounds_max, device=boxes_ref.device)
    centre = boxes_ref[..., :3]
    inside = ((centre >= lo) & (centre < hi)).all(dim=-1)                  # B×K
    return boxes_ref, valid.bool() & inside


class DetectorTask(nn.Module):
    """`forward(batch) -> {"loss", metrics…}`; `exported_modules()` -> {"mapper", "detector"}."""

    def __init__(self, *, config: DetectorTaskConfig) -> None:
        super().__init__()
        self.cfg = c = config
        self.mapper = Mapper(grid=c.grid, width=c.encoder_width, feature_dim=c.feature_dim,
                             full_res=c.encoder_full_res)
        self.detector = Detector3D(grid=c.grid, in_channels=c.feature_dim, width=c.width,
                                   head_width=c.head_width, stride=c.stride, anchor_sizes=c.anchor_sizes,
                                   anchor_y=c.anchor_y)
        if c.freeze_features:
            self.mapper.requires_grad_(False)
        self.frozen_maps = (FrozenMapCache(max_bytes=c.frozen_map_cache_mb << 20)
                            if c.freeze_features and c.frozen_map_cache_mb > 0 else None)
        self._generator = torch.Generator().manual_seed(c.seed) if c.seed is not None else None

    @staticmethod
    def from_preset(preset: Preset, *, labels: int | None = None, freeze_features: bool = True,
                    init: str | None = None, **overrides) -> "DetectorTask":
        """Task at a preset's sizes. labels: label budget (None: every record); freeze_features: keep
        the mapper fixed; init: a bundle directory whose `mapper` (and `detector`, if any) weights are
        loaded now (the training CLI's --init does the same through the loop); `overrides` replace
        DetectorTaskConfig fields."""
        grid = preset.grid
        base = dict(grid=grid, feature_dim=preset.feature_dim, encoder_width=preset.encoder_width,
                    encoder_full_res=preset.encoder_full_res,
                    width=2 * preset.feature_dim, head_width=4 * preset.feature_dim,
                    stride=default_stride(grid), anchor_y=preset.ground_y - CAR_HALF_HEIGHT_M,
                    labels=labels, freeze_features=freeze_features)
        base.update(overrides)
        task = DetectorTask(config=DetectorTaskConfig(**base))
        if init is not None:
            task.load_modules_from_bundle(init)
        return task

    def load_modules_from_bundle(self, bundle_dir: str) -> list[str]:
        """Copy the weights of a bundle's `mapper`/`detector` into this task; returns the names loaded."""
        from core.bundle import load_bundle
        from core.errors import BundleError

        bundle = load_bundle(bundle_dir, torch.device("cpu"))
        loaded = []
        for name, module in self.exported_modules().items():
            if name in bundle.modules:
                module.load_state_dict(bundle.modules[name].state_dict())
                loaded.append(name)
        if "mapper" not in loaded:
            raise BundleError(f"{bundle_dir}: bundle has no 'mapper' module (has {sorted(bundle.modules)})")
        return loaded

    def exported_modules(self) -> dict[str, nn.Module]:
        return {"mapper": self.mapper, "detector": self.detector}

    def train(self, mode: bool = True) -> "DetectorTask":
        super().train(mode)
        if self.cfg.freeze_features:
            self.mapper.eval()  # frozen features keep their BatchNorm statistics as loaded
        return self

    def _randint(self, n: int) -> int:
        return int(torch.randint(n, (1,), generator=self._generator).item())

    def build_map(self, batch: dict[str, torch.Tensor], t: int) -> torch.Tensor:
        """The latent map of time t in ref_t from all views: B×F×Z×Y×X."""
        rgb, depth = batch["rgb"][:, t], batch["depth"][:, t]      # B×V×3×H×W, B×V×H×W
        poses = cam_T_ref(batch, t, t)                            # B×V×4×4
        if self.cfg.freeze_features:
            if self.training and self.frozen_maps is not None and self.frozen_maps.enabled:  # each example's map alone, kept
                return self.frozen_maps.maps(self.mapper, rgb, depth, batch["pix_T_cam"], poses)
            with torch.no_grad():
                return self.mapper(rgb, depth, batch["pix_T_cam"], poses)
        return self.mapper(rgb, depth, batch["pix_T_cam"], poses)

    def labelled(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Which records carry box labels under the label budget: B bool."""
        B = batch["rgb"].shape[0]
        device = batch["rgb"].device
        if self.cfg.labels is None:
            return torch.ones(B, dtype=torch.bool, device=device)
        if "record_index" not in batch:
            raise DataError("detector: labels=N needs the batch's 'record_index' (B int64: each record's "
                            "index in its dataset) to know which records carry box labels")
        index = batch["record_index"].to(device).reshape(B)
        return index < self.cfg.labels

    def forward(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """batch: `core.data.batch.records_to_batch` output with boxes (+ record_index if labels=N)."""
        T = batch["rgb"].shape[1]
        t = self._randint(T)
        features = self.build_map(batch, t)                         # B×F×Z×Y×X
        logits, deltas = self.detector(features)                    # B×N, B×N×6
        boxes_ref, keep = gt_boxes_ref(batch, t, self.cfg.grid)     # B×K×7, B×K
        labelled = self.labelled(batch)                             # B
        anchors = self.detector.anchors                             # N×6

        obj_losses, box_losses = [], []
        num_pos, num_gt, pos_prob, neg_prob = [], [], [], []
        for b in range(logits.shape[0]):
            if not bool(labelled[b]):
                continue
            gt = boxes_to_aabb(boxes_ref[b, keep[b]])              # G×6
            labels, matched = assign_anchors(anchors, gt, positive_iou=self.cfg.positive_iou,
                                             negative_iou=self.cfg.negative_iou)
            pos, neg = sample_anchors(labels, num_samples=self.cfg.num_samples,
                                      positive_fraction=self.cfg.positive_fraction, generator=self._generator)
            sampled = pos | neg                                     # N
            n_sampled = max(1, int(sampled.sum()))
            obj_losses.append(F.binary_cross_entropy_with_logits(
                logits[b, sampled], pos[sampled].to(logits.dtype), reduction="sum") / n_sampled)
            if bool(pos.any()):
                target = encode_deltas(anchors[pos], gt[matched[pos]])  # P×6
                box_losses.append(F.smooth_l1_loss(deltas[b, pos], target, beta=self.cfg.smooth_l1_beta,
                                                   reduction="sum") / n_sampled)
            else:
                box_losses.append(deltas[b].sum() * 0.0)
            num_pos.append(float(pos.sum()))
            num_gt.append(float(gt.shape[0]))
            with torch.no_grad():
                probs = torch.sigmoid(logits[b])
                if bool(pos.any()):
                    pos_prob.append(probs[labels == 1].mean())
                neg_prob.append(probs[labels == 0].mean() if bool((labels == 0).any()) else probs.mean())

        zero = (logits.sum() + deltas.sum()) * 0.0  # keeps the graph (and DDP) intact without labels
        n_lab = len(obj_losses)
        loss_obj = torch.stack(obj_losses).sum() / n_lab if n_lab else zero
        loss_box = torch.stack(box_losses).sum() / n_lab if n_lab else zero
        loss = loss_obj + self.cfg.box_weight * loss_box
        metrics = {
            "loss_obj": loss_obj.detach(), "loss_box": loss_box.detach(),
            "labelled": labelled.float().mean(),
            "num_pos": torch.tensor(sum(num_pos) / n_lab if n_lab else 0.0),
            "num_gt": torch.tensor(sum(num_gt) / n_lab if n_lab else 0.0),
            "prob_pos": torch.stack(pos_prob).mean() if pos_prob else torch.tensor(0.0),
            "prob_neg": torch.stack(neg_prob).mean() if neg_prob else torch.tensor(0.0),
        }
        return {"loss": loss, **{k: v.detach().float().to(logits.device) for k, v in metrics.items()}}
