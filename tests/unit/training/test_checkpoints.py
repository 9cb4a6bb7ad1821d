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


def test_a_run_with_a_weight_average_needs_its_average_whole(tmp_path):
    """ema_decay > 0: a checkpoint whose average file is missing or cut short is not complete (every resume
    failed on it instead of falling back); a run without an average needs none."""
    from services.training.checkpoints import is_complete
    from services.training.weight_average import WeightAverage

    task, opt = _trained_task_and_optimizer()
    average = WeightAverage(task, decay=0.9)
    for step in (2, 4, 6):
        save_checkpoint(tmp_path / checkpoint_dir_name(step), task=task, optimizer=opt, step=step,
                        config={"ema_decay": 0.9}, metrics={}, average=average)
    assert all(is_complete(tmp_path / checkpoint_dir_name(step)) for step in (2, 4, 6))
    cut = tmp_path / checkpoint_dir_name(6) / "average.safetensors"
    cut.write_bytes(cut.read_bytes()[:20])
    (tmp_path / checkpoint_dir_name(4) / "average.safetensors").unlink()
    assert read_checkpoint_state(newest_complete_checkpoint(tmp_path)).step == 2
    plain = tmp_path / "plain" / checkpoint_dir_name(2)
    save_checkpoint(plain, task=task, optimizer=opt, step=2, config={"ema_decay": 0.0}, metrics={})
    assert is_complete(plain)


def _staged(root, task, opt, step: int):
    import tempfile
    from pathlib import Path

    root.mkdir(parents=True, exist_ok=True)
    directory = Path(tempfile.mkdtemp(prefix=f".staging_{step}_", dir=root))
    save_checkpoint(directory, task=task, optimizer=opt, step=step, config={"task": "toy"}, metrics={})
    return directory


@pytest.mark.parametrize("cut", ["replacing", "pruning"])
def test_a_commit_cut_short_while_deleting_leaves_only_complete_checkpoints(tmp_path, monkeypatch, cut):
    """A second Ctrl-C stops at once, possibly inside commit's deletion of the checkpoint it replaces (the signal's
    checkpoint at a step that already has one) or of the one it prunes: every dir the store still lists loads."""
    import shutil

    import services.training.checkpoints as checkpoints

    task, opt = _trained_task_and_optimizer()
    root = tmp_path / "checkpoints"
    store = LocalCheckpointStore(root, keep=2)
    store.commit(_staged(root, task, opt, 5), 5)
    store.commit(_staged(root, task, opt, 10), 10)
    real_rmtree = shutil.rmtree

    def cut_short(path, *args, **kwargs):   # one file gone, then the interrupt
        (tmp_path / "seen").write_text(str(path))
        (checkpoints.Path(path) / checkpoints.TASK_FILE).unlink(missing_ok=True)
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoints.shutil, "rmtree", cut_short)
    with pytest.raises(KeyboardInterrupt):
        store.commit(_staged(root, task, opt, 10 if cut == "replacing" else 15), 10 if cut == "replacing" else 15)
    monkeypatch.setattr(checkpoints.shutil, "rmtree", real_rmtree)
    assert checkpoints.RETIRED_PREFIX in (tmp_path / "seen").read_text()   # what was being deleted had been renamed
    for directory in store.list():
        fresh = ToyTask()
        fresh.register_buffer("counter", torch.tensor(0, dtype=torch.int64))
        load_checkpoint(directory, task=fresh, optimizer=torch.optim.Adam(fresh.parameters()))
    assert store.latest().name == checkpoint_dir_name(10 if cut == "replacing" else 15)
    store.commit(_staged(root, task, opt, 20), 20)   # the next commit clears what the cut one left
    assert not list(root.glob(f"{checkpoints.RETIRED_PREFIX}*"))
    assert [p.name for p in store.list()] == [checkpoint_dir_name(s) for s in ((10, 20) if cut == "replacing"
                                                                              else (15, 20))]


def test_the_driver_passes_over_checkpoints_cut_short(tmp_path):
    """The run's newest checkpoint, as the driver picks it to export or to skip a finished run
    (latest_checkpoint_dir), is a complete one, as the workers pick theirs: not a Ray copy with truncated weights,
    and a torn state.json in an older one does not stop the rerun."""
    from services.training.config import TrainJobConfig
    from services.training.job import latest_checkpoint_dir

    task, opt = _trained_task_and_optimizer()
    config = TrainJobConfig(task="pretrain", data_dir=str(tmp_path / "data"), run_dir=str(tmp_path / "run"),
                            workers=2, steps=4).resolved()
    ray_root = config.run_path / config.ray_storage_name
    for step in (2, 3, 4):
        save_checkpoint(ray_root / checkpoint_dir_name(step), task=task, optimizer=opt, step=step,
                        config=config.to_dict(), metrics={})
    weights = ray_root / checkpoint_dir_name(4) / "task.safetensors"
    weights.write_bytes(weights.read_bytes()[:20])                                  # the final copy cut short
    (ray_root / checkpoint_dir_name(2) / "state.json").write_text('{"step": 2, "conf')   # an older one torn
    assert latest_checkpoint_dir(config) == ray_root / checkpoint_dir_name(3)
    assert newest_complete_checkpoint(ray_root) == ray_root / checkpoint_dir_name(3)
    optimizer = ray_root / checkpoint_dir_name(3) / "optimizer.pt"   # a copy cut short inside the optimizer file
    optimizer.write_bytes(optimizer.read_bytes()[:100])
    assert latest_checkpoint_dir(config) is None and newest_complete_checkpoint(ray_root) is None


def test_commit_flushes_the_checkpoint_to_disk_before_it_becomes_the_newest(tmp_path, monkeypatch):
    """Every file of the staged checkpoint and its folder are fsynced before the rename that makes it the newest,
    and the store's folder after it (before older checkpoints are deleted): a power loss cannot leave the newest
    name over empty files while the older ones are gone."""
    import os

    task, opt = _trained_task_and_optimizer()
    store = LocalCheckpointStore(tmp_path / "ckpts", keep=1)
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))),
                                                 real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", str(a), str(b))), real_replace(a, b))[1])
    staged = tmp_path / "staged"
    save_checkpoint(staged, task=task, optimizer=opt, step=5, config={}, metrics={})
    final = store.commit(staged, 5)
    rename = next(i for i, e in enumerate(events) if e[0] == "replace" and e[2] == str(final))
    flushed = {e[1] for e in events[:rename] if e[0] == "fsync"}
    files = {str(staged / p.name) for p in final.iterdir()}   # their names when flushed, before the rename
    assert len(files) == 3 and files <= flushed and str(staged) in flushed
    assert ("fsync", str(store.root)) in events[rename:]
