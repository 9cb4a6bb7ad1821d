"""Checkpoint round trip (task + optimizer + step + config), the local store, and run identity."""

import pytest
import torch

from services.training.checkpoints import (
    CheckpointError, LocalCheckpointStore, check_same_run, checkpoint_dir_name, load_checkpoint, newest_complete_checkpoint,
    read_checkpoint_state, save_checkpoint,
)
from tests.unit.training.toy import ToyTask


def _trained_task_and_optimizer():
    torch.manual_seed(0)
    task = ToyTask()
    task.register_buffer("counter", torch.tensor(7, dtype=torch.int64))  # non-float buffers survive too
    opt = torch.optim.Adam(task.parameters(), lr=0.1)
    for _ in range(3):
        opt.zero_grad()
        task({"x": torch.randn(4, 3), "y": torch.randn(4)})["loss"].backward()
        opt.step()
    return task, opt


def test_round_trip_restores_weights_optimizer_and_step(tmp_path):
    task, opt = _trained_task_and_optimizer()
    config = {"task": "toy", "task_options": {}, "preset": "tiny"}
    save_checkpoint(tmp_path / "c", task=task, optimizer=opt, step=3, config=config,
                    metrics={"loss": torch.tensor(0.25)})

    fresh = ToyTask()
    fresh.register_buffer("counter", torch.tensor(0, dtype=torch.int64))
    fresh_opt = torch.optim.Adam(fresh.parameters(), lr=0.1)
    state = load_checkpoint(tmp_path / "c", task=fresh, optimizer=fresh_opt)

    assert state.step == 3 and state.config == config and state.metrics == {"loss": 0.25}
    for name, tensor in task.state_dict().items():
        assert torch.equal(fresh.state_dict()[name], tensor), name
    # Optimizer moments restored: one more identical step gives identical weights.
    batch = {"x": torch.ones(2, 3), "y": torch.zeros(2)}
    for t, o in ((task, opt), (fresh, fresh_opt)):
        o.zero_grad()
        t(batch)["loss"].backward()
        o.step()
    assert torch.equal(task.head.weight, fresh.head.weight)


def test_load_rejects_a_checkpoint_of_another_model(tmp_path):
    task, opt = _trained_task_and_optimizer()
    save_checkpoint(tmp_path / "c", task=task, optimizer=opt, step=1, config={}, metrics={})
    with pytest.raises(CheckpointError, match="does not fit this task"):
        load_checkpoint(tmp_path / "c", task=torch.nn.Linear(2, 2))


def test_missing_or_corrupt_state_is_a_clear_error(tmp_path):
    with pytest.raises(CheckpointError, match="missing state.json"):
        read_checkpoint_state(tmp_path)
    (tmp_path / "state.json").write_text("{not json")
    with pytest.raises(CheckpointError, match="corrupt state.json"):
        read_checkpoint_state(tmp_path)


def test_local_store_keeps_the_newest(tmp_path):
    task, opt = _trained_task_and_optimizer()
    store = LocalCheckpointStore(tmp_path / "ckpts", keep=2)
    assert store.latest() is None
    for step in (5, 10, 15):
        staged = tmp_path / f"staged{step}"
        save_checkpoint(staged, task=task, optimizer=opt, step=step, config={}, metrics={})
        store.commit(staged, step)
    assert [read_checkpoint_state(p).step for p in store.list()] == [10, 15]
    assert read_checkpoint_state(store.latest()).step == 15
    (store.root / "checkpoint_00000020").mkdir()  # half-written (no state.json): ignored
    assert read_checkpoint_state(store.latest()).step == 15


def test_check_same_run_names_the_difference(tmp_path):
    identity = {"task": "pretrain", "task_options": {"objective": "contrastive"}, "preset": "tiny"}
    check_same_run(dict(identity, steps=5), identity, tmp_path)
    other = dict(identity, task_options={"objective": "regression"})
    with pytest.raises(CheckpointError, match="task_options"):
        check_same_run(other, identity, tmp_path)


def test_newest_complete_checkpoint_passes_over_a_copy_cut_short(tmp_path):
    # What a Ray worker group restarted before the controller registered its last report falls back to.
    task, opt = _trained_task_and_optimizer()
    for step in (2, 4, 6):
        save_checkpoint(tmp_path / checkpoint_dir_name(step), task=task, optimizer=opt, step=step, config={},
                        metrics={})
    weights = tmp_path / checkpoint_dir_name(6) / "task.safetensors"
    weights.write_bytes(weights.read_bytes()[:10])          # truncated weights
    (tmp_path / checkpoint_dir_name(4) / "optimizer.pt").unlink()  # a file never copied
    found = newest_complete_checkpoint(tmp_path)
    assert found is not None and read_checkpoint_state(found).step == 2
    assert newest_complete_checkpoint(tmp_path / "absent") is None
