"""The weight average (services/training/weight_average.py) against a slow per-element reference, and its
place in the loop: kept in checkpoints, resumed exactly, exported, refused where it does not fit."""

import pytest
import torch
from torch import nn

from services.training.checkpoints import (
    AVERAGE_FILE, CheckpointError, load_checkpoint, read_checkpoint_state, save_checkpoint,
)
from services.training.config import TrainConfigError, TrainJobConfig
from services.training.loop import train_loop
from services.training.sessions import LocalSession
from services.training.weight_average import WeightAverage, warmed_decay
from tests.unit.training.toy import toy_records, toy_spec


def _tiny_module() -> nn.Module:
    torch.manual_seed(0)
    return nn.Sequential(nn.Linear(3, 4), nn.BatchNorm1d(4))   # parameters, float buffers, an int buffer


def _reference_average(snapshots: list[dict], decay: float) -> dict:
    """Slow, obvious: a[0] = snapshot 0; after step t (1-based) a = d_t a + (1 - d_t) w_t, element by element,
    with d_t = min(decay, (1 + t) / (10 + t)); integer entries take the newest value."""
    average = {k: v.clone().double() if v.is_floating_point() else v.clone() for k, v in snapshots[0].items()}
    for t, weights in enumerate(snapshots[1:], start=1):
        d = min(decay, (1.0 + t) / (10.0 + t))
        for name, w in weights.items():
            if w.is_floating_point():
                flat_a, flat_w = average[name].view(-1), w.double().view(-1)
                for i in range(flat_a.numel()):
                    flat_a[i] = d * flat_a[i] + (1.0 - d) * flat_w[i]
            else:
                average[name] = w.clone()
    return average


def test_average_follows_the_reference_over_steps_of_changing_weights():
    module = _tiny_module()
    average = WeightAverage(module, decay=0.9)
    snapshots = [{k: v.clone() for k, v in module.state_dict().items()}]
    optimizer = torch.optim.SGD(module.parameters(), lr=0.1)
    for step in range(1, 31):
        module.train()
        loss = module(torch.randn(8, 3)).pow(2).mean()          # also moves BatchNorm's running stats
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        average.update(module, step=step)
        snapshots.append({k: v.clone() for k, v in module.state_dict().items()})
    expected = _reference_average(snapshots, 0.9)
    for name, value in average.state_dict().items():
        if value.is_floating_point():
            torch.testing.assert_close(value.double(), expected[name], rtol=1e-5, atol=1e-6)
        else:
            assert torch.equal(value, expected[name]), name
    # the average lags: it is not the last weights
    assert not torch.allclose(average.state_dict()["0.weight"], module.state_dict()["0.weight"])


def test_warm_up_lowers_the_decay_only_while_steps_are_few():
    assert warmed_decay(0.995, 1) == pytest.approx(2 / 11)
    assert warmed_decay(0.995, 90) == pytest.approx(91 / 100)
    assert warmed_decay(0.995, 5000) == 0.995


@pytest.mark.parametrize("decay", [0.0, 1.0, -0.5])
def test_decay_outside_the_open_interval_is_refused(decay):
    with pytest.raises(ValueError, match="decay must lie in"):
        WeightAverage(_tiny_module(), decay=decay)


def test_checkpoint_keeps_the_average_and_loads_it_on_request(tmp_path):
    module = _tiny_module()
    average = WeightAverage(module, decay=0.5)
    with torch.no_grad():
        module[0].weight.add_(1.0)
    average.update(module, step=100)                             # halfway: weight + 0.5
    optimizer = torch.optim.Adam(module.parameters())
    save_checkpoint(tmp_path / "c", task=module, optimizer=optimizer, step=3, config={}, metrics={},
                    average=average)
    last, averaged = _tiny_module(), _tiny_module()
    load_checkpoint(tmp_path / "c", task=last)
    load_checkpoint(tmp_path / "c", task=averaged, averaged_weights=True)
    torch.testing.assert_close(last[0].weight, module[0].weight)
    torch.testing.assert_close(averaged[0].weight, module[0].weight - 0.5)
    restored = WeightAverage(_tiny_module(), decay=0.5)
    load_checkpoint(tmp_path / "c", task=_tiny_module(), average=restored)
    torch.testing.assert_close(restored.state_dict()["0.weight"], averaged[0].weight)


def test_resuming_an_averaging_run_from_a_checkpoint_without_one_is_refused(tmp_path):
    module = _tiny_module()
    save_checkpoint(tmp_path / "c", task=module, optimizer=torch.optim.Adam(module.parameters()), step=1,
                    config={}, metrics={})
    with pytest.raises(CheckpointError, match=f"missing {AVERAGE_FILE}"):
        load_checkpoint(tmp_path / "c", task=_tiny_module(), average=WeightAverage(_tiny_module(), decay=0.9))
    # without an average the checkpoint loads its last weights even when they are asked for averaged
    load_checkpoint(tmp_path / "c", task=_tiny_module(), averaged_weights=True)


def _config(tmp_path, name="run", **overrides) -> TrainJobConfig:
    base = dict(task="toy", data_dir=str(tmp_path / "unused"), run_dir=str(tmp_path / name), preset="tiny",
                steps=30, batch_size=4, lr=0.05, checkpoint_every=10, log_every=10, device="cpu", ema_decay=0.9)
    return TrainJobConfig(**{**base, **overrides}).resolved()


def _run(config, records):
    return train_loop(config, LocalSession(config, dataset=records), toy_spec())


def _latest_weights(config, *, averaged: bool) -> dict:
    task = toy_spec().build(config, torch.device("cpu"))
    load_checkpoint(LocalSession(config, dataset=[]).store.latest(), task=task, averaged_weights=averaged)
    return {k: v.clone() for k, v in task.state_dict().items()}


def test_a_resumed_run_continues_the_saved_average(tmp_path):
    records = toy_records(32)
    _run(_config(tmp_path, steps=10), records)
    average_10 = _latest_weights(_config(tmp_path, steps=10), averaged=True)
    _run(_config(tmp_path, steps=11), records)                   # resumes at 10, one step, checkpoints at 11
    weights_11 = _latest_weights(_config(tmp_path, steps=11), averaged=False)
    average_11 = _latest_weights(_config(tmp_path, steps=11), averaged=True)
    d = warmed_decay(0.9, 11)
    for name in average_11:
        torch.testing.assert_close(average_11[name], d * average_10[name] + (1 - d) * weights_11[name])
    assert not torch.allclose(average_11["head.weight"], weights_11["head.weight"])
    state = read_checkpoint_state(LocalSession(_config(tmp_path, steps=11), dataset=[]).store.latest())
    assert state.step == 11 and state.config["ema_decay"] == 0.9


def test_resume_refuses_another_decay(tmp_path):
    records = toy_records(8)
    _run(_config(tmp_path, steps=10), records)
    with pytest.raises(CheckpointError, match="ema_decay: checkpoint 0.9 vs now 0.0"):
        _run(_config(tmp_path, steps=20, ema_decay=0.0), records)


def test_decay_out_of_range_is_a_config_error(tmp_path):
    with pytest.raises(TrainConfigError, match="--ema-decay must lie in"):
        _config(tmp_path, ema_decay=1.0)


@pytest.mark.parametrize("field, value, message", [
    ("lr", float("inf"), "--lr must be > 0"), ("lr", float("nan"), "--lr must be > 0"), ("lr", 0.0, "--lr must be > 0"),
    ("gpus_per_worker", float("nan"), "--gpus-per-worker must be >= 0"),
    ("gpus_per_worker", float("inf"), "--gpus-per-worker must be >= 0")])
def test_non_finite_numbers_are_config_errors(tmp_path, field, value, message):
    # NaN compares false both ways, so a plain `< 0` let it through (found by an audit of the CLI)
    with pytest.raises(TrainConfigError, match=message):
        _config(tmp_path, **{field: value})
