"""Occupancy scores at many thresholds from one pass, and the balanced threshold chosen from them."""

import math

import pytest
import torch

from core.bundle import Bundle
from core.eval.protocols.occupancy import (
    THRESHOLD_GRID, OccupancyEvalConfig, balanced_threshold, choose_balanced_threshold, evaluate,
    scores_by_threshold,
)
from core.presets import get_preset
from core.synthetic import generate_record
from core.tasks import build_task

TINY = get_preset("tiny")


def _scores(pairs):
    return {th: {"acc_occupied": a, "acc_free": b} for th, (a, b) in pairs.items()}


def test_balanced_threshold_maximises_the_worse_class_and_ties_go_to_the_middle():
    # lowering the threshold trades free accuracy for occupied accuracy; 0.3 is the best worst case
    scores = _scores({0.2: (0.99, 0.90), 0.3: (0.96, 0.95), 0.4: (0.94, 0.97), 0.5: (0.93, 0.99)})
    assert balanced_threshold(scores) == 0.3
    assert balanced_threshold(_scores({0.3: (0.9, 0.9), 0.45: (0.9, 0.9), 0.7: (0.9, 0.9)})) == 0.45
    # a class without labels (NaN) never wins against a defined one
    assert balanced_threshold(_scores({0.1: (math.nan, 1.0), 0.5: (0.2, 0.3)})) == 0.5


def test_scores_by_threshold_equal_one_evaluation_per_threshold():
    torch.manual_seed(0)
    task = build_task("occupancy", TINY).eval()
    bundle = Bundle(preset=TINY, modules=dict(task.exported_modules()))
    records = [generate_record(TINY, seed=s, num_frames=1) for s in (5, 6)]
    thresholds = (0.2, 0.5, 0.8)
    fast = scores_by_threshold(bundle, records, thresholds, device="cpu")
    assert list(fast) == list(thresholds)
    for th in thresholds:
        slow = evaluate(bundle, records, OccupancyEvalConfig(threshold=th), device="cpu")["scores"]
        assert fast[th] == pytest.approx(slow, nan_ok=True)
    # occupied accuracy cannot rise as the threshold does, free accuracy cannot fall
    occ = [fast[th]["acc_occupied"] for th in thresholds]
    free = [fast[th]["acc_free"] for th in thresholds]
    assert occ == sorted(occ, reverse=True) and free == sorted(free)
    assert THRESHOLD_GRID[0] == 0.05 and THRESHOLD_GRID[-1] == 0.95 and len(THRESHOLD_GRID) == 19


def test_every_view_scores_pool_the_voxels_of_each_single_view_evaluation():
    """input_views=None counts each record's every view as the input in turn: the accuracies equal the
    voxel-weighted pool of one `evaluate` per view, and the chosen threshold is the balanced one of those."""
    torch.manual_seed(0)
    task = build_task("occupancy", TINY).eval()
    bundle = Bundle(preset=TINY, modules=dict(task.exported_modules()))
    records = [generate_record(TINY, seed=s, num_frames=1) for s in (5, 6)]
    V = records[0]["rgb"].shape[1]
    assert V > 1
    thresholds = (0.3, 0.5)
    pooled = scores_by_threshold(bundle, records, thresholds, input_views=None, device="cpu")
    for th in thresholds:
        per_view = [evaluate(bundle, records, OccupancyEvalConfig(input_view=v, threshold=th), device="cpu")["scores"]
                    for v in range(V)]
        for cls in ("occupied", "free"):
            n = sum(s[f"voxels_{cls}"] for s in per_view)
            correct = sum(s[f"acc_{cls}"] * s[f"voxels_{cls}"] for s in per_view)
            assert pooled[th][f"voxels_{cls}"] == n
            assert pooled[th][f"acc_{cls}"] == pytest.approx(correct / n)
    # one view listed explicitly is that view's evaluation
    one = scores_by_threshold(bundle, records, thresholds, input_views=(1,), device="cpu")
    assert one[0.5] == pytest.approx(
        evaluate(bundle, records, OccupancyEvalConfig(input_view=1, threshold=0.5), device="cpu")["scores"], nan_ok=True)
    every = scores_by_threshold(bundle, records, input_views=None, device="cpu")
    threshold, at = choose_balanced_threshold(bundle, records, device="cpu")
    assert threshold == balanced_threshold(every) and at == every[threshold]


def test_labels_hold_every_voxel_the_models_own_input_holds():
    # the synthetic ground lies exactly on a voxel face: the test labels must put it where the mapper's input
    # (and the occupancy task's training labels) put it — small records 3 and 4 had 8 and 11 input-occupied
    # voxels labelled not occupied when the labels were computed from float64 points
    from core.eval.protocols.inputs import record_batch
    from core.eval.protocols.occupancy import _frames
    from core.models.input_volume import input_volume
    from core.tasks.poses import cam_T_ref

    small = get_preset("small")
    task = build_task("pretrain", small, objective="contrastive").eval()
    modules = task.exported_modules()
    bundle = Bundle(preset=small, modules={"mapper": modules["mapper"], "occupancy": modules["occupancy"]})
    for seed in (3, 4):
        record = generate_record(small, seed=seed, num_frames=1)
        batch = record_batch(record, "cpu")
        cam = cam_T_ref(batch, 0, 0)
        volume, _ = input_volume(batch["rgb"][:, 0, 0], batch["depth"][:, 0, 0], batch["pix_T_cam"][:, 0], cam[:, 0],
                                 small.grid)                                   # 1×4×Z×Y×X: view 0's input
        (_, _, _, occupied, free), = list(_frames(bundle, [record], (0,), "cpu"))
        in_input = volume[:, :1] > 0
        assert int(in_input.sum()) > 1000
        assert not bool((in_input & ~occupied).any()) and not bool((in_input & free).any())
