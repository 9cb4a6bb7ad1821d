"""with_stabilising_pose: record poses that stabilise frame 1 with a given pose, frame 1's view geometry
unchanged — checked against the definitions (and the pitfall it exists for: world_T_ref1 alone cancels)."""

import torch

from core.eval.protocols.inputs import pair_inputs, record_batch, with_stabilising_pose
from core.geometry import se3
from core.pipeline.stabilise import poses_ref0_T_ref1
from core.presets import TINY
from core.synthetic.generate import generate_record
from core.tasks.poses import rig_cam_T_ref


def _inputs():
    record = generate_record(TINY, seed=4, num_frames=2, moving_ego=True)
    return {k: v.double() for k, v in pair_inputs(record_batch(record, "cpu"), 0, 1).items()}


def test_the_given_pose_stabilises_and_frame_ones_own_geometry_stays():
    inputs = _inputs()
    wanted = se3.random_rigid(1, 0.01, 0.2, torch.Generator().manual_seed(0), dtype=torch.float64)
    moved = with_stabilising_pose(inputs, wanted)
    stabilise = poses_ref0_T_ref1(moved["world_T_cam0"], moved["world_T_cam1"], moved["world_T_ref0"],
                                  moved["world_T_ref1"])
    torch.testing.assert_close(stabilise, wanted, rtol=1e-6, atol=1e-5)
    torch.testing.assert_close(rig_cam_T_ref(moved["world_T_cam1"], moved["world_T_ref1"]),
                               rig_cam_T_ref(inputs["world_T_cam1"], inputs["world_T_ref1"]), rtol=1e-6, atol=1e-5)
    # frame 1 lifted into ref0 (cam1_T_ref0 = cam1_T_ref1 · ref1_T_ref0) moves by the error, and offsetting
    # world_T_ref1 alone would not move it at all
    def cam1_T_ref0(x):
        pose = poses_ref0_T_ref1(x["world_T_cam0"], x["world_T_cam1"], x["world_T_ref0"], x["world_T_ref1"])
        return rig_cam_T_ref(x["world_T_cam1"], x["world_T_ref1"]) @ se3.invert(pose)[:, None]
    offset_only = {**inputs, "world_T_ref1": inputs["world_T_ref1"] @ wanted}
    torch.testing.assert_close(cam1_T_ref0(offset_only), cam1_T_ref0(inputs), rtol=1e-6, atol=1e-5)
    assert (cam1_T_ref0(moved) - cam1_T_ref0(inputs)).abs().max() > 1e-3
    # the true pose gives the inputs back
    true_pose = se3.invert(inputs["world_T_ref0"]) @ inputs["world_T_ref1"]
    same = with_stabilising_pose(inputs, true_pose)
    for key in ("world_T_ref1", "world_T_cam1"):
        torch.testing.assert_close(same[key], inputs[key], rtol=1e-6, atol=1e-5)
