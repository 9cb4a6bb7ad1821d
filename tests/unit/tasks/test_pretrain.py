"""Pretraining step: batch assembly, both objectives run, and the loss goes down on a generated record."""

import numpy as np
import pytest
import torch

from core.data.batch import records_to_batch
from core.errors import DataError, ShapeError
from core.geometry.shift import shift_voxels
from core.presets import TINY, CameraConfig, TrainDefaults
from core.synthetic import generate_record
from core.tasks import build_task

# The tiny preset with half-size images and fewer planes keeps each step well under a second on CPU.
FAST = TINY.with_overrides(camera=CameraConfig(H=32, W=96, hfov_deg=90.0), depth_planes=16,
                           train=TrainDefaults(batch_size=2, contrastive_samples=64))


@pytest.fixture(scope="module")
def records():
    return [generate_record(FAST, seed=s, num_frames=1) for s in (0, 1)]


def test_records_to_batch_shapes_and_types(records):
    batch = records_to_batch(records)
    T, V, H, W = records[0]["depth"].shape
    assert batch["rgb"].shape == (2, T, V, 3, H, W) and batch["rgb"].dtype == torch.float32
    assert 0.0 <= batch["rgb"].min() and batch["rgb"].max() <= 1.0
    assert torch.equal(batch["rgb"][1, 0, 2, 1], torch.from_numpy(records[1]["rgb"][0, 2, :, :, 1]).float() / 255)
    assert batch["depth"].shape == (2, T, V, H, W)
    assert batch["pix_T_cam"].shape == (2, V, 4, 4) and batch["world_T_ref"].shape == (2, T, 4, 4)
    assert batch["box_valid"].dtype == torch.bool and batch["box_id"].dtype == torch.int32


def test_records_to_batch_rejects_mismatched_records(records):
    other = dict(records[1], depth=np.zeros((1, 2, 3, 4), np.float32))
    with pytest.raises(DataError, match="depth"):
        records_to_batch([records[0], other])
    with pytest.raises(DataError, match="rgb"):
        records_to_batch([{k: v for k, v in records[0].items() if k != "rgb"}])


@pytest.mark.parametrize("objective,keys", [
    ("contrastive", {"loss_2d", "loss_3d", "loss_l2_2d", "loss_l2_3d", "loss_occ"}),
    ("regression", {"rgb_l1", "loss_occ"})])
def test_task_returns_finite_scalars_and_exports(records, objective, keys):
    task = build_task("pretrain", FAST, objective=objective, seed=0)
    out = task(records_to_batch(records))
    assert keys <= set(out) and "loss" in out
    assert all(v.ndim == 0 and torch.isfinite(v) for v in out.values())
    out["loss"].backward()
    expected = {"mapper", "projector", "occupancy"} | ({"net2d"} if objective == "contrastive" else set())
    assert set(task.exported_modules()) == expected


def test_task_rejects_single_view_and_unknown_objective(records):
    with pytest.raises(ValueError, match="objective"):
        build_task("pretrain", FAST, objective="vae")
    one_view = records_to_batch(records)
    one_view = {k: (v[:, :, :1] if k in ("rgb", "depth", "world_T_cam") else v[:, :1] if k == "pix_T_cam" else v)
                for k, v in one_view.items()}
    with pytest.raises(ShapeError, match="2 views"):
        build_task("pretrain", FAST, seed=0)(one_view)


@pytest.mark.parametrize("objective,metrics", [("contrastive", ("loss_2d", "loss_3d")), ("regression", ("rgb_l1",))])
def test_loss_decreases_in_process(records, objective, metrics):
    torch.manual_seed(0)
    task = build_task("pretrain", FAST, objective=objective, seed=0, free_space_stride=4)
    opt = torch.optim.Adam(task.parameters(), lr=1e-3)
    batch = records_to_batch(records)
    history = []
    for _ in range(25):
        out = task(batch)
        opt.zero_grad()
        out["loss"].backward()
        opt.step()
        history.append((out["loss"].item(), sum(out[m].item() for m in metrics)))
    loss = np.array(history)  # steps × (total, view objective); views and samples are random per step
    assert loss[-5:, 0].mean() < 0.95 * loss[:5, 0].mean(), loss[:, 0]
    assert loss[-5:, 1].mean() < loss[:5, 1].mean(), loss[:, 1]


@pytest.mark.parametrize("objective", ["contrastive", "regression"])
def test_local_matching_term_trains_the_encoder(records, objective):
    """coeff_match > 0 adds loss_match / match_hit (core.losses.local_matching on a moved block of one
    view's input volume) to either objective; its gradient reaches the encoder."""
    task = build_task("pretrain", FAST, objective=objective, seed=0, coeff_match=1.0, match_samples=32)
    out = task(records_to_batch(records))
    assert {"loss_match", "match_hit"} <= set(out)
    assert float(out["loss_match"]) > 0 and 0.0 <= float(out["match_hit"]) <= 1.0
    task.zero_grad()
    out["loss"].backward()
    grads_with = [p.grad.clone() for p in task.mapper.encoder.parameters()]
    plain = build_task("pretrain", FAST, objective=objective, seed=0)
    plain.load_state_dict(task.state_dict())
    plain_out = plain(records_to_batch(records))
    assert "loss_match" not in plain_out
    plain_out["loss"].backward()
    # same views and samples (same seed), so the gradients differ by the matching term's only
    assert any(not torch.allclose(a, p.grad) for a, p in zip(grads_with, plain.mapper.encoder.parameters()))


def test_shift_positives_is_validated():
    with pytest.raises(ValueError, match="shift_positives needs objective='contrastive'"):
        build_task("pretrain", FAST, objective="regression", shift_positives=2)
    with pytest.raises(ValueError, match="shift_positives must be >= 0"):
        build_task("pretrain", FAST, objective="contrastive", shift_positives=-1)


def test_shift_positives_realigns_the_target_features(records, monkeypatch):
    """With a pointwise encoder (exactly shift-equivariant), the target view lifted into a moved grid and its
    features moved back are the aligned step's bottom-up map wherever the match stayed inside the grid, and
    only there are the 3D positives valid (captured at the dense L2 term, which sees the same maps as the
    contrastive one)."""
    import core.tasks.pretrain as pretrain_module
    seen = []
    monkeypatch.setattr(pretrain_module, "dense_l2",
                        lambda top, bottom, valid: seen.append((top, bottom, valid)) or (top - bottom).square().mean())

    def bottom_up(offset):
        task = build_task("pretrain", FAST, objective="contrastive", seed=0, shift_positives=2)
        torch.manual_seed(0)
        task.mapper.encoder = torch.nn.Conv3d(4, task.cfg.feature_dim, 1, bias=False)
        task._positive_offset = lambda: offset
        task(records_to_batch(records))
        top, bottom, valid = seen[-2]  # the 3D term (the 2D one follows)
        return top, bottom, valid

    top0, bottom0, valid0 = bottom_up((0, 0, 0))
    top1, bottom1, valid1 = bottom_up((2, -1, 1))
    inside = torch.zeros_like(valid0)
    inside[..., :-1, 1:, :-2] = 1  # p + (dx, dy, dz) = p + (2, -1, 1) inside the grid
    assert torch.equal(top1, top0)
    assert torch.equal(valid1, valid0 * inside) and int(valid1.sum()) > 0
    assert torch.allclose(bottom1 * inside, bottom0 * inside, atol=1e-6)
    assert not torch.allclose(bottom0 * inside, shift_voxels(bottom0, (2, -1, 1)) * inside, atol=1e-3)


def test_shift_positives_off_draws_nothing(records):
    """shift_positives=0 leaves the step as it was: same losses from the same seed."""
    a = build_task("pretrain", FAST, objective="contrastive", seed=3)
    b = build_task("pretrain", FAST, objective="contrastive", seed=3, shift_positives=0)
    b.load_state_dict(a.state_dict())
    out_a, out_b = a(records_to_batch(records)), b(records_to_batch(records))
    assert float(out_a["loss"]) == float(out_b["loss"])


def _projector_input(task, batch) -> torch.Tensor:
    """The map the target view is rendered from (the projector's first input) in one training step."""
    seen = []
    handle = task.projector.register_forward_hook(lambda module, args, out: seen.append(args[0].detach().clone()))
    try:
        task(batch)
    finally:
        handle.remove()
    return seen[0]


@pytest.mark.parametrize("objective,options", [("contrastive", {}), ("regression", {}),
                                               ("regression", {"coeff_match": 1.0})])
def test_the_held_out_view_does_not_reach_the_map_it_is_predicted_from(records, objective, options):
    # In training mode BatchNorm normalises by its batch: encoded with the input views, the target would
    # pass its statistics into the map. Replacing the target view (same seed: same t and target) must leave
    # the map the projector renders bit-identical.
    batch = records_to_batch(records)
    task = build_task("pretrain", FAST, objective=objective, seed=0, **options)
    task.train()
    t, target = task._randint(1), task._randint(batch["rgb"].shape[2])   # the draws of the next step
    other = {k: v.clone() for k, v in batch.items()}
    other["rgb"][:, t, target] = torch.rand_like(other["rgb"][:, t, target])
    other["depth"][:, t, target] = other["depth"][:, t, target].flip(-1)
    maps = []
    for b in (batch, other):
        torch.manual_seed(0)   # the same initial weights
        task = build_task("pretrain", FAST, objective=objective, seed=0, **options)
        task.train()
        maps.append(_projector_input(task, b))
    assert torch.equal(maps[0], maps[1])


def test_regression_scores_only_the_pixels_the_map_can_know(records):
    # colours where the target view has no depth return (sky) or sees beyond the grid are not in any input
    # view's volume: the regression loss must not depend on them
    batch = records_to_batch(records)
    task = build_task("pretrain", FAST, objective="regression", seed=0)
    t, target = task._randint(1), task._randint(batch["rgb"].shape[2])
    other = {k: v.clone() for k, v in batch.items()}
    other["depth"][:, t, target, :, : other["depth"].shape[-1] // 2] = 0.0    # the left half: no depth
    losses = []
    for rgb_left in (0.0, 1.0):
        b = {k: v.clone() for k, v in other.items()}
        b["rgb"][:, t, target, :, :, : b["rgb"].shape[-1] // 2] = rgb_left
        torch.manual_seed(0)   # the same initial weights
        task = build_task("pretrain", FAST, objective="regression", seed=0)
        losses.append(task(b)["rgb_l1"])
    assert torch.equal(losses[0], losses[1])
