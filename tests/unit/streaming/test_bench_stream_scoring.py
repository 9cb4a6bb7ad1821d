"""tests/benchmarks/bench_stream.py's scoring of published boxes against the synthetic world's true movers."""

import numpy as np

from core.eval.moving_protocol import gt_moving_boxes
from core.presets import get_preset
from core.synthetic import generate_record
from tests.benchmarks.bench_stream import box_accuracy


def test_a_box_on_each_mover_scores_and_one_beyond_the_episodes_grid_is_not_a_false_positive():
    tiny = get_preset("tiny")
    record = generate_record(tiny, seed=0, num_views=1, num_frames=2)   # the camera's episode, as box_accuracy
    gt = np.asarray(gt_moving_boxes(record, 0, tiny.grid, min_points=10)).reshape(-1, 7)   # in ref_0
    assert len(gt) >= 1
    # the boxes as the bridge publishes them: in the camera's frame at frame 0
    world_T_cam = record["world_T_cam"][0, 0].astype(np.float64)
    cam_T_ref = np.linalg.inv(world_T_cam) @ record["world_T_ref"][0].astype(np.float64)
    centres = gt[:, :3] @ cam_T_ref[:3, :3].T + cam_T_ref[:3, 3]
    yaw_offset = float(np.arctan2(cam_T_ref[0, 2], cam_T_ref[0, 0]))   # ref -> cam about y (level rigs)
    assert np.allclose(cam_T_ref[1, :3], [0, 1, 0], atol=0.3)
    boxes = [dict(zip(("x", "y", "z", "lx", "ly", "lz", "yaw"), [*c, *g[3:6], g[6] - yaw_offset]), score=0.9)
             for c, g in zip(centres, gt)]
    beyond = dict(x=0.0, y=0.0, z=500.0, lx=4.0, ly=1.5, lz=2.0, yaw=0.0, score=0.99)    # 500 m ahead
    lines = [{"sequence": 0, "boxes": []},
             {"sequence": 1, "boxes": [*boxes, beyond], "world_T_frame": world_T_cam.tolist()}]
    acc = box_accuracy("tiny", 2, lines)
    assert acc["outside_grid"] == 1 and acc["published_boxes"] == len(gt) and acc["true_movers"] == len(gt)
    assert acc["precision@0.25"] == acc["recall@0.25"] == 1.0
