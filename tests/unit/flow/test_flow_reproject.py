"""Re-unprojected synthetic pairs (FlowTaskConfig.reproject_fraction): frame t lifted after the scene moved
by a known rigid motion, checked against the plain ways of building the same volume."""

import math

import pytest
import torch

from core.data.batch import records_to_batch
from core.geometry import se3
from core.models.flow_synthetic import REPROJECT_RANGES, rigid_flow, sample_motions
from core.presets import TINY
from core.synthetic.generate import generate_record
from core.tasks.flow import FlowTask


def _batch():
    return records_to_batch([generate_record(TINY, seed=3, num_frames=2)])


def _shift_x(volume: torch.Tensor, k: int) -> torch.Tensor:
    """B×C×Z×Y×X content moved by k voxels along +x, zeros where nothing came from (the obvious way)."""
    out = torch.zeros_like(volume)
    out[..., k:] = volume[..., :-k]
    return out


def test_identity_motion_rebuilds_frame_t_and_a_one_voxel_move_shifts_it():
    task = FlowTask.from_preset(TINY, seed=0, inputs="volume")
    batch = _batch()
    v0, _, occupied = task.flow_inputs(batch, 0)
    same = task.reprojected_input(batch, 0, torch.eye(4)[None])
    torch.testing.assert_close(same, v0)
    # the scene moved by exactly one voxel along x: every depth point lands one voxel further along x
    motion = se3.from_rt(torch.eye(3)[None], torch.tensor([[TINY.grid.voxel_size, 0.0, 0.0]]))
    moved = task.reprojected_input(batch, 0, motion)
    expected = _shift_x(occupied, 1)
    got = (moved[:, :1] > 0).float()
    inner = (slice(None), slice(None), slice(None), slice(None), slice(1, None))
    mismatch = float((got[inner] != expected[inner]).float().sum()) / float(expected[inner].sum())
    assert expected.sum() > 100 and mismatch < 0.02, mismatch   # points on a voxel face may round either way
    # and the true flow of that move is one voxel along x everywhere
    torch.testing.assert_close(rigid_flow(motion, TINY.grid)[0, 0], torch.ones(TINY.grid.Z, TINY.grid.Y, TINY.grid.X))


def test_feature_inputs_are_the_mapper_of_the_reprojected_frame():
    task = FlowTask.from_preset(TINY, seed=0, inputs="features").eval()
    batch = _batch()
    f0, _, _ = task.flow_inputs(batch, 0)
    torch.testing.assert_close(task.reprojected_input(batch, 0, torch.eye(4)[None]), f0)


def test_reproject_motions_cycle_large_small_jitter_within_their_ranges():
    M, kinds = sample_motions(9, generator=torch.Generator().manual_seed(0), ranges=REPROJECT_RANGES)
    assert sorted(kinds) == sorted(["large", "small", "jitter"] * 3)
    for T, kind in zip(M, kinds):
        deg, metres = REPROJECT_RANGES[kind]
        assert float(T[:3, 3].abs().max()) <= metres + 1e-6
        assert math.degrees(float(se3.rotation_angle(T[:3, :3]))) <= math.sqrt(3) * deg + 1e-4
    jitter = M[[k == "jitter" for k in kinds]]
    assert float(jitter[:, :3, 3].abs().max()) > 0   # not the identity: a re-unprojected zero motion is a copy


def test_training_steps_with_every_rigid_step_reprojected_are_finite():
    task = FlowTask.from_preset(TINY, seed=0, inputs="volume", reproject_fraction=1.0, object_fraction=0.0)
    task.train()
    batch = _batch()
    for _ in range(2):
        out = task(batch)
        assert torch.isfinite(out["loss"]) and torch.isfinite(out["synth_epe"])
        out["loss"].backward()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_reprojected_input_and_a_reprojected_training_step_on_cuda_match_cpu():
    batch = _batch()
    motion = se3.random_rigid(1, 0.05, 0.5, torch.Generator().manual_seed(1))
    for inputs in ("volume", "features"):
        torch.manual_seed(0)
        task = FlowTask.from_preset(TINY, seed=0, inputs=inputs, reproject_fraction=1.0, object_fraction=0.0)
        cpu = task.reprojected_input(batch, 0, motion)
        task_cuda = task.to("cuda")
        gpu = task_cuda.reprojected_input({k: v.to("cuda") for k, v in batch.items()}, 0, motion.to("cuda"))
        # voxelisation: a point on a voxel face may round either way on the two devices
        differ = float(((gpu.cpu() - cpu).abs() > 1e-3).float().mean())
        assert differ < 0.01, (inputs, differ)
        out = task_cuda.train()({k: v.to("cuda") for k, v in batch.items()})
        assert out["loss"].is_cuda and torch.isfinite(out["loss"])
        out["loss"].backward()
