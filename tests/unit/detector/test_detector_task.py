"""The detector task on tiny synthetic records: overfitting, the label budget, bundles and the pipeline."""

from __future__ import annotations

import pytest
import torch

from core.bundle import load_bundle, save_bundle
from core.data.batch import records_to_batch
from core.errors import DataError
from core.models.detector_boxes import aabb_iou, boxes_to_aabb
from core.models.detector_targets import assign_anchors
from core.presets import TINY
from core.synthetic import generate_record
from core.tasks import build_task
from core.tasks.detector import DetectorTask, gt_boxes_ref


@pytest.fixture(scope="module")
def records():
    # One time step each, so every training step sees the same map and boxes.
    return [generate_record(TINY, seed=s, num_frames=1) for s in (3, 4)]


def _gt_aabb(batch, b=0):
    boxes, keep = gt_boxes_ref(batch, 0, TINY.grid)
    return boxes_to_aabb(boxes[b, keep[b]])  # G×6


def test_gt_boxes_move_to_ref_and_keep_inside_grid(records):
    batch = records_to_batch(records[:1])
    boxes_ref, keep = gt_boxes_ref(batch, 0, TINY.grid)
    world_T_ref = batch["world_T_ref"][0, 0].double()
    for k in range(boxes_ref.shape[1]):
        centre_world = torch.tensor(records[0]["boxes"][0, k, :3], dtype=torch.float64)
        # slow reference: solve world_T_ref · p_ref = p_world
        p = torch.linalg.solve(world_T_ref, torch.cat([centre_world, torch.ones(1, dtype=torch.float64)]))
        torch.testing.assert_close(boxes_ref[0, k, :3].double(), p[:3], atol=1e-4, rtol=0)
        lo, hi = torch.tensor(TINY.grid.bounds_min), torch.tensor(TINY.grid.bounds_max)
        inside = bool(((p[:3] >= lo) & (p[:3] < hi)).all())
        assert bool(keep[0, k]) == (inside and bool(records[0]["box_valid"][0, k]))
    assert int(keep.sum()) >= 1


def test_detector_overfits_one_record(records):
    torch.manual_seed(0)
    batch = records_to_batch(records[:1])
    task = build_task("detector", TINY, seed=0)   # frozen random features: the paper's random-init baseline
    assert isinstance(task, DetectorTask) and not any(p.requires_grad for p in task.mapper.parameters())
    opt = torch.optim.Adam([p for p in task.parameters() if p.requires_grad], lr=3e-3)
    task.train()
    for _ in range(40):
        out = task(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
    # Observed at step 40 (train mode): P(object) ≈ 0.99 on positive anchors, ≈ 0.01 on negatives.
    assert out["prob_pos"] > 0.9 and out["prob_neg"] < 0.05

    task.eval()
    with torch.no_grad():
        logits, deltas = task.detector(task.build_map(batch, 0))
        dets = task.detector.decode(logits, deltas)[0]
    gt = _gt_aabb(batch)
    labels, _ = assign_anchors(task.detector.anchors, gt, positive_iou=0.45, negative_iou=0.3)
    prob = torch.sigmoid(logits[0])
    # Eval mode (BatchNorm running statistics) is less sharp after 40 steps; observed ratio ≈ 75.
    assert prob[labels == 1].mean() > 5 * prob[labels == 0].mean()
    assert dets["boxes"].shape[1] == 7 and bool((dets["boxes"][:, 6] == 0).all())
    assert bool((dets["scores"][:-1] >= dets["scores"][1:]).all())
    top_iou = aabb_iou(dets["boxes"][:1, :6], gt).max().item()
    assert top_iou > 0.5  # observed ≈ 0.78


def test_label_budget_masks_records_beyond_n(records):
    batch = records_to_batch(records)
    task = DetectorTask.from_preset(TINY, labels=1, seed=0)
    task.eval()  # no batch coupling through BatchNorm, so per-record losses compare exactly

    batch["record_index"] = torch.tensor([5, 7])          # both beyond the budget
    out = task(batch)
    assert out["loss"].item() == 0.0 and out["labelled"].item() == 0.0
    out["loss"].backward()
    assert all(p.grad is None or not p.grad.any() for p in task.detector.parameters())

    batch["record_index"] = torch.tensor([0, 7])          # only the first record is labelled
    mixed = DetectorTask.from_preset(TINY, labels=1, seed=0)
    mixed.load_state_dict(task.state_dict())
    mixed.eval()
    out_mixed = mixed(batch)
    single = DetectorTask.from_preset(TINY, labels=1, seed=0)
    single.load_state_dict(task.state_dict())
    single.eval()
    first = records_to_batch(records[:1])
    first["record_index"] = torch.tensor([0])
    out_single = single(first)
    assert out_mixed["labelled"].item() == 0.5
    assert out_mixed["loss"].item() > 0
    torch.testing.assert_close(out_mixed["loss"], out_single["loss"])

    del batch["record_index"]
    with pytest.raises(DataError, match="record_index"):
        task(batch)


def test_bundle_round_trip_and_pipeline_detect(records, tmp_path):
    from core.pipeline.detect import detect, detections_per_item

    torch.manual_seed(1)
    task = DetectorTask.from_preset(TINY, seed=0)
    with torch.no_grad():  # non-trivial BatchNorm statistics and objectness weights
        for m in task.detector.modules():
            if isinstance(m, (torch.nn.BatchNorm2d, torch.nn.BatchNorm3d)):
                m.running_mean.normal_()
                m.running_var.uniform_(0.5, 2.0)
        task.detector.objectness.weight.normal_(std=0.5)
    task.eval()
    save_bundle(tmp_path / "b", modules=task.exported_modules(), preset=TINY, provenance={"task": "detector"})
    bundle = load_bundle(tmp_path / "b", "cpu")
    assert set(bundle.modules) == {"mapper", "detector"}
    assert bundle.modules["detector"].config() == task.detector.config()

    batch = records_to_batch(records)
    with torch.no_grad():
        features = task.build_map(batch, 0)
        want = task.detector.detect(features, min_score=0.02)
    out = detect(bundle, batch["rgb"][:, 0], batch["depth"][:, 0], batch["pix_T_cam"],
                 batch["world_T_cam"][:, 0], batch["world_T_ref"][:, 0], min_score=0.02)
    assert out["boxes"].shape[:2] == out["scores"].shape == out["valid"].shape
    got = detections_per_item(out)
    for g, w in zip(got, want):
        assert g["scores"].numel() == w["scores"].numel() > 0
        torch.testing.assert_close(g["boxes"], w["boxes"], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(g["scores"], w["scores"], atol=1e-5, rtol=1e-4)
        assert bool((g["scores"] >= 0.02).all())


def test_label_subset_holds_the_first_n_records(records, tmp_path):
    import numpy as np

    from core.data.shards import ShardDataset, write_dataset
    from core.errors import ConfigError
    from services.training.label_subset import labelled_subset

    data = tmp_path / "data"
    write_dataset(data, records, split="train", preset_name="tiny", grid=TINY.grid.to_dict(),
                  generator={"source": "test"}, seed=0)
    run = tmp_path / "run"
    subset = ShardDataset(labelled_subset(data, run, 1))
    source = ShardDataset(data)
    assert len(subset) == 1 and subset.key(0) == source.key(0)
    for key, value in source[0].items():
        np.testing.assert_array_equal(subset[0][key], value)
    assert labelled_subset(data, run, 1) == run / "labelled_data"    # a rerun reuses it
    with pytest.raises(ConfigError, match="1 records from record 0"):
        labelled_subset(data, run, 2)
    # a later draw: records [first, first + n) of the source, in order; a range past the end is refused
    later = ShardDataset(labelled_subset(data, tmp_path / "run1", 1, first=1))
    assert [later.key(i) for i in range(len(later))] == [source.key(1)]
    np.testing.assert_array_equal(later[0]["rgb"], source[1]["rgb"])
    with pytest.raises(ConfigError, match="from record 1"):
        labelled_subset(data, tmp_path / "run1", 1)            # the run dir was trained on another draw
    with pytest.raises(ConfigError, match=r"records \[1, 3\)"):
        labelled_subset(data, tmp_path / "run2", 2, first=1)
