"""core.pipeline.moving: the moving-object pipeline on a tiny synthetic pair.

With freshly initialised modules the boxes mean nothing, so the first tests check the contract
(keys, shapes, padding, boxes inside the grid, the routes' exact keyword set). The post-processing is
checked on ground-truth 3D flow of a record holding one moving car: it must find that car, and the
box must overlap the true box in ref0 (IoU > 0.3: 1 m voxels and the voxel-padded fit make the box
coarse at the tiny preset, so a tighter bound would test the grid, not the code).
"""

import numpy as np
import pytest
import torch

from core.bundle import Bundle
from core.data.batch import records_to_batch
from core.data.ground_truth import gt_flow
from core.eval.iou3d import iou_3d
from core.geometry import se3
from core.geometry.boxes import transform_boxes
from core.pipeline import moving_objects
from core.pipeline.flow import estimate_flow
from core.pipeline.moving import MovingObjectsConfig, boxes_from_flow
from core.presets import TINY
from core.synthetic import default_world_config, generate_record
from core.tasks.egomotion import EgomotionTask
from core.tasks.flow import FlowTask
from core.tasks.occupancy import OccupancyTask

GRID = TINY.grid


@pytest.fixture(scope="module")
def one_car_record():
    world = default_world_config(TINY).with_overrides(num_vehicles=(1, 1), moving_fraction=1.0)
    return generate_record(TINY, seed=5, world=world)


@pytest.fixture(scope="module")
def bundle():
    torch.manual_seed(0)
    flow_task = FlowTask.from_preset(TINY)
    # an untrained flow module predicts exactly zero (its last convs start at zero); give them small
    # random weights so the post-processing has motion to work on
    with torch.no_grad():
        for p in flow_task.flow.parameters():
            if p.dim() > 1 and not p.any():
                p.normal_(std=0.05)
    modules = {"mapper": flow_task.mapper, "flow": flow_task.flow,
               "occupancy": OccupancyTask.from_preset(TINY).occupancy,
               "egomotion": EgomotionTask.from_preset(TINY).egomotion}
    return Bundle(preset=TINY, modules={k: m.eval() for k, m in modules.items()})


def _pair(record, *, with_ref: bool) -> dict:
    b = records_to_batch([{k: record[k] for k in ("rgb", "depth", "pix_T_cam", "world_T_cam", "world_T_ref")}])
    pair = {"rgb0": b["rgb"][:, 0], "depth0": b["depth"][:, 0], "pix_T_cam0": b["pix_T_cam"],
            "world_T_cam0": b["world_T_cam"][:, 0], "rgb1": b["rgb"][:, 1], "depth1": b["depth"][:, 1],
            "pix_T_cam1": b["pix_T_cam"], "world_T_cam1": b["world_T_cam"][:, 1]}
    if with_ref:
        pair.update(world_T_ref0=b["world_T_ref"][:, 0], world_T_ref1=b["world_T_ref"][:, 1])
    return pair


def _check_contract(out, B):
    K = out["boxes"].shape[1]
    assert K >= 1
    assert out["boxes"].shape == (B, K, 7) and out["scores"].shape == (B, K)
    assert out["valid"].shape == (B, K) and out["valid"].dtype == torch.bool
    assert out["velocities"].shape == (B, K, 3)
    assert out["flow"].shape == (B, 3, *GRID.shape_zyx) and out["ref0_T_ref1"].shape == (B, 4, 4)
    assert torch.all(out["boxes"][~out["valid"]] == 0) and torch.all(out["scores"][~out["valid"]] == 0)
    v = out["valid"]
    assert torch.isfinite(out["boxes"][v]).all() and torch.isfinite(out["velocities"][v]).all()
    assert ((out["scores"][v] >= -1) & (out["scores"][v] <= 1)).all()
    # a box covers voxels of the grid: its centre lies inside the bounds
    lo, hi = torch.tensor(GRID.bounds_min), torch.tensor(GRID.bounds_max)
    centres = out["boxes"][v][:, :3]
    assert ((centres >= lo) & (centres <= hi)).all()


def test_routes_keyword_set_and_contract(bundle, one_car_record):
    # exactly the keys services/inference/routes.py passes (no world_T_ref: ref = camera of view 0)
    out = moving_objects(bundle, **_pair(one_car_record, with_ref=False))
    _check_contract(out, 1)


def test_everything_moves_gives_boxes_in_the_grid(bundle, one_car_record):
    # occupancy threshold below every probability and no speed threshold: the random flow moves every
    # voxel, so there is at least one component and its box must stay within the grid
    cfg = MovingObjectsConfig(min_speed=0.0, min_object_speed=0.0, occupied_above=-1.0, occupancy="predicted",
                              ground_margin=None)
    pair = _pair(one_car_record, with_ref=True)
    out = moving_objects(bundle, **pair, stabilize="poses", config=cfg)
    _check_contract(out, 1)
    assert out["valid"].any()
    # the same as running the post-processing on estimate_flow's output by hand
    flow = estimate_flow(bundle, **pair, stabilize="poses", occupancy_threshold=-1.0)
    again = boxes_from_flow(flow["flow"], flow["occupancy"], GRID, cfg)
    assert torch.allclose(again["boxes"], out["boxes"]) and torch.equal(again["valid"], out["valid"])


def test_egomotion_stabilisation_is_used_when_the_bundle_has_it(bundle, one_car_record):
    pair = _pair(one_car_record, with_ref=True)
    out = moving_objects(bundle, **pair)
    est = bundle.modules["egomotion"]
    assert est is not None
    from core.pipeline.egomotion import estimate_egomotion
    expected = estimate_egomotion(bundle, **pair)["ref0_T_ref1"]
    assert torch.allclose(out["ref0_T_ref1"], expected, atol=1e-5)


def test_ground_truth_flow_finds_the_moving_car(one_car_record):
    rec = one_car_record
    assert rec["box_moving"][rec["box_valid"][0]].sum() == 1
    flow = gt_flow(rec, 0, GRID)[None]                                       # 1×3×Z×Y×X
    # The true flow moves the voxels whose centres lie in the car: boxes of their centres pad one voxel.
    out = boxes_from_flow(flow, None, GRID, MovingObjectsConfig(moving_voxels="centres"))
    assert int(out["valid"].sum()) == 1
    k = int(np.flatnonzero(rec["box_valid"][0] & rec["box_moving"])[0])
    ref_T_world = se3.invert(torch.as_tensor(rec["world_T_ref"][0:1], dtype=torch.float64))
    gt_box = transform_boxes(ref_T_world, torch.as_tensor(rec["boxes"][0:1, k:k + 1], dtype=torch.float64))[0]
    iou = iou_3d(out["boxes"][0, :1].double().numpy(), gt_box.numpy())[0, 0]
    assert iou > 0.3, iou
    # the velocity is the box's displacement over dt (m/s), the same direction as the true motion
    gt_box1 = transform_boxes(ref_T_world, torch.as_tensor(rec["boxes"][1:2, k:k + 1], dtype=torch.float64))[0]
    true_v = (gt_box1[0, :3] - gt_box[0, :3]) / MovingObjectsConfig().dt
    v = out["velocities"][0, 0].double()
    assert torch.dot(v, true_v) / (v.norm() * true_v.norm()) > 0.9


def _same_but_for_rounding_across_horizontal_faces(ours: torch.Tensor, reference: torch.Tensor) -> None:
    """ours, reference: Z×Y×X bool voxelised points. Every difference is a point that rounded across a
    horizontal voxel face (the flat ground lies on one): the other side of that face holds the
    reference's voxel or ours."""
    differ = ours ^ reference
    assert differ.sum() <= 0.15 * reference.sum()
    either = ours | reference
    neighbour = torch.zeros_like(either)
    neighbour[:, 1:] |= either[:, :-1]
    neighbour[:, :-1] |= either[:, 1:]
    assert (neighbour[differ]).all()


def test_default_boxes_use_observed_voxels_above_the_ground(bundle, one_car_record):
    """The default post-processing = boxes_from_flow on the head-gated flow with frame 0's observed
    voxels and its fitted ground plane, computed here by hand from the record's points."""
    from core.data.ground_truth import gt_occupancy, points_in_ref
    from core.moving.ground import fit_ground_plane
    from core.pipeline.moving import frame_evidence
    from core.geometry.poses import rig_cam_T_ref

    cfg = MovingObjectsConfig(min_speed=0.0)
    pair = _pair(one_car_record, with_ref=True)
    out = moving_objects(bundle, **pair, stabilize="poses", config=cfg)
    evidence = frame_evidence(pair["depth0"], pair["pix_T_cam0"],
                              rig_cam_T_ref(pair["world_T_cam0"], pair["world_T_ref0"]), GRID)
    # observed voxels = the record's own voxelised depth points (an independent float64 path through
    # ground_truth; points exactly on a voxel face, like the flat ground, may round to either side)
    ours, reference = evidence.observed[0, 0].bool(), gt_occupancy(one_car_record, 0, GRID)[0].bool()  # Z×Y×X
    _same_but_for_rounding_across_horizontal_faces(ours, reference)
    # which view saw each voxel: each view's own voxelised points, their union the observed voxels
    V = pair["depth0"].shape[1]
    assert evidence.seen_by.shape == (1, V, *GRID.shape_zyx)
    assert torch.equal(evidence.seen_by.any(dim=1), evidence.observed[:, 0].bool())
    for v in range(V):
        _same_but_for_rounding_across_horizontal_faces(evidence.seen_by[0, v],
                                                       gt_occupancy(one_car_record, 0, GRID, views=[v])[0].bool())
    xyz, valid = points_in_ref(one_car_record, 0)
    plane = fit_ground_plane(xyz[valid].double().numpy())
    assert plane is not None and np.allclose(evidence.ground[0], plane, atol=1e-3)
    flow = estimate_flow(bundle, **pair, stabilize="poses")
    again = boxes_from_flow(flow["flow"], evidence.observed, GRID, cfg, ground=evidence.ground)
    assert torch.allclose(again["boxes"], out["boxes"]) and torch.equal(again["valid"], out["valid"])
    # no box reaches below the ground: the bottom face of every box lies on or above the plane
    boxes = out["boxes"][out["valid"]].double()  # K×7
    a, b, c, d = plane
    bottom_heights = a * boxes[:, 0] + b * (boxes[:, 1] + boxes[:, 4] / 2) + c * boxes[:, 2] + d  # y down
    assert (bottom_heights >= -0.05 * GRID.voxel_size).all()
