"""Occupancy accuracy on labelled voxels (the paper's appendix protocol).

Per record and step t: the map is built from ONE view (`input_view`), and the labels are the union of
that view's and the next view's (occupied = voxelised points, free = ray traversal; unlabelled voxels are
ignored), made the way the occupancy task makes its training labels and the mapper its input
(core.tasks.occupancy_labels on the batch, float32): the synthetic ground lies exactly on a voxel face,
and labels computed another way (ground_truth's float64 points) put it in the row above for some records
— voxels the model's own input holds scored as free. Scores: accuracy for occupied / free / all labelled
voxels and occupied IoU (definitions: core.eval.occupancy_metrics). `evaluate` scores one threshold;
`scores_by_threshold` many from one pass of the model, and `balanced_threshold` picks among them the one
whose worse class accuracy is highest; `choose_balanced_threshold` does so on held-out records with each
of their views as the input in turn (bench paper chooses it on its validation records and scores the test
records there).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from core.data.ground_truth import gt_occupancy
from core.errors import ConfigError
from core.eval.occupancy_metrics import add_counts, occupancy_counts, occupancy_scores
from core.eval.protocols.inputs import record_batch
from core.tasks.occupancy_labels import occupancy_labels
from core.tasks.poses import cam_T_ref

NEEDS = ("mapper", "occupancy")


@dataclass(frozen=True, kw_only=True)
class OccupancyEvalConfig:
    input_view: int = 0       # the single view the map is built from
    threshold: float = 0.5    # P(occupied) at or above which a voxel counts as occupied


# Thresholds `balanced_threshold` chooses among: 0.05, 0.10, ..., 0.95.
THRESHOLD_GRID = tuple(round(0.05 * k, 2) for k in range(1, 20))


def _frames(bundle, records, input_views: Sequence[int] | None, device):
    """Per record, input view and step: (record, t, prob 1×1×Z×Y×X, occupied, free 1×1×Z×Y×X bool labels).
    `input_views` None: every view of each record in turn."""
    grid = bundle.preset.grid
    mapper, head = bundle.modules["mapper"], bundle.modules["occupancy"]
    for record in records:
        batch = record_batch(record, device)
        T, V = batch["rgb"].shape[1:3]
        for input_view in (range(V) if input_views is None else input_views):
            if not 0 <= input_view < V:
                raise ConfigError(f"--input-view {input_view}: records have {V} views")
            label_views = sorted({input_view, (input_view + 1) % V})
            v = [input_view]
            for t in range(T):
                cam = cam_T_ref(batch, t, t)  # 1×V×4×4
                features = mapper(batch["rgb"][:, t][:, v], batch["depth"][:, t][:, v], batch["pix_T_cam"][:, v],
                                  cam[:, v])
                prob = head.probabilities(features)  # 1×1×Z×Y×X
                occ, free = occupancy_labels(batch["depth"][:, t][:, label_views],
                                             batch["pix_T_cam"][:, label_views], cam[:, label_views], grid)
                yield record, t, prob, occ, free


@torch.no_grad()
def evaluate(bundle, records, config: OccupancyEvalConfig = OccupancyEvalConfig(), *, device) -> dict:
    """{"scores": core.eval.occupancy_metrics.occupancy_scores, "frames", "example": {"prob", "occ",
    "input"} Z×Y×X arrays of the first frame (prediction, occupied labels, the input view's points)}."""
    counts: dict = {}
    example = None
    frames = 0
    for record, t, prob, occ, free in _frames(bundle, records, (config.input_view,), device):
        counts = add_counts(counts, occupancy_counts(prob, occ, free, threshold=config.threshold))
        frames += 1
        if example is None:
            example = {"prob": prob[0, 0].cpu().numpy(), "occ": occ[0, 0].cpu().numpy().astype(np.float32),
                       "input": gt_occupancy(record, t, bundle.preset.grid, [config.input_view])[0].numpy()}
    return {"scores": occupancy_scores(counts), "frames": frames, "example": example}


@torch.no_grad()
def scores_by_threshold(bundle, records, thresholds=THRESHOLD_GRID, *, input_views: Sequence[int] | None = (0,),
                        device) -> dict:
    """{threshold: occupancy_scores} over `records`, every threshold from one pass of the model; the voxels
    of every input view in `input_views` (None: every view of each record) counted together."""
    counts: dict = {float(th): {} for th in thresholds}
    for _, _, prob, occ, free in _frames(bundle, records, input_views, device):
        for th in counts:
            counts[th] = add_counts(counts[th], occupancy_counts(prob, occ, free, threshold=th))
    return {th: occupancy_scores(c) for th, c in counts.items()}


def choose_balanced_threshold(bundle, records, *, device) -> tuple[float, dict]:
    """(threshold, its occupancy_scores on `records`): the balanced threshold (`balanced_threshold`) on
    held-out `records`, each record's every view taken as the single input view in turn.

    Why every view: the threshold is chosen on few records (bench paper's 8 validation records) and the
    worse class accuracy moves by ~0.005 per 0.05 step of the threshold there, so one view's frames chose a
    step below the best on 2 of 3 small modules; with every view (4× the frames, the same kind of map) the
    choice matched the best one for the scored records on 11 of 12 modules (README, "Occupancy")."""
    scores = scores_by_threshold(bundle, records, input_views=None, device=device)
    threshold = balanced_threshold(scores)
    return threshold, scores[threshold]


def balanced_threshold(scores: dict) -> float:
    """The threshold of `scores_by_threshold` output whose worse class accuracy is highest (the balanced
    operating point: occupied and free voxels count alike), ties to the one nearest 0.5.

    Why: the class-balanced loss leaves the probabilities' 0.5 point off balance when one class is harder
    (occupied voxels only the other view sees), so a fixed 0.5 reports the head's bias as much as its
    features. Choose it on held-out records, never on the records it is then scored on."""
    def worse(th: float) -> float:
        s = scores[th]
        a, b = s["acc_occupied"], s["acc_free"]
        return -1.0 if a != a or b != b else min(a, b)  # NaN (a class without labels) never wins

    return max(scores, key=lambda th: (worse(th), -abs(th - 0.5)))
