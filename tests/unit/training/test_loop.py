"""The shared training loop in the in-process session, on a toy task: learning, resume, NaN guard."""

import math

import pytest

from services.training.checkpoints import read_checkpoint_state
from services.training.config import TrainJobConfig
from services.training.loop import train_loop
from services.training.progress import read_metrics
from services.training.sessions import LocalSession
from tests.unit.training.toy import toy_records, toy_spec


def _config(tmp_path, **overrides) -> TrainJobConfig:
    base = dict(task="toy", data_dir=str(tmp_path / "unused"), run_dir=str(tmp_path / "run"),
                preset="tiny", steps=40, batch_size=4, lr=0.05, checkpoint_every=10, log_every=1,
                device="cpu")
    return TrainJobConfig(**{**base, **overrides}).resolved()


def _run(config, records, spec=None):
    return train_loop(config, LocalSession(config, dataset=records), spec or toy_spec())


def test_loss_decreases_and_checkpoints_land_every_n_steps(tmp_path):
    config = _config(tmp_path)
    outcome = _run(config, toy_records(32))
    assert outcome.status == "finished" and outcome.step == 40 and outcome.start_step == 0
    losses = [r["loss"] for r in read_metrics(config.metrics_path)]
    assert len(losses) == 40
    assert sum(losses[-5:]) < 0.2 * sum(losses[:5])
    store = LocalSession(config, dataset=[]).store
    assert [read_checkpoint_state(p).step for p in store.list()] == [30, 40]  # keep_checkpoints=2


def test_rerun_resumes_from_the_latest_checkpoint(tmp_path):
    records = toy_records(32)
    first = _config(tmp_path, steps=20)
    _run(first, records)
    second = _config(tmp_path, steps=30)  # same run dir, more steps
    outcome = _run(second, records)
    assert outcome.start_step == 20 and outcome.step == 30
    steps = [r["step"] for r in read_metrics(second.metrics_path)]
    assert steps == list(range(1, 31))  # the rerun continued at 21, nothing repeated
    # A third run with nothing left to do trains no step.
    again = _run(second, records)
    assert again.start_step == again.step == 30


def test_a_run_cut_into_chunks_draws_at_each_step_what_an_uninterrupted_one_draws(tmp_path):
    # the benchmark's stopping rules train in chunks, each a resume: the task's random draws must go on,
    # not restart with every call (they once replayed the first chunk's draws in every chunk)
    records = toy_records(32)
    whole: list[float] = []
    _run(_config(tmp_path / "whole", steps=12, checkpoint_every=4), records, toy_spec(draws=whole))
    chunked: list[float] = []
    for steps in (4, 8, 12):
        _run(_config(tmp_path / "chunked", steps=steps, checkpoint_every=4), records, toy_spec(draws=chunked))
    assert len(whole) == len(chunked) == 12 and chunked == whole
    assert len(set(chunked)) == 12          # no chunk repeats another's draws
    other: list[float] = []
    _run(_config(tmp_path / "other", steps=4, seed=1), records, toy_spec(draws=other))
    assert other != whole[:4]               # another run seed draws otherwise


def test_step_seeds_differ_by_seed_rank_and_step():
    from services.training.seeding import shuffle_seed, step_seed

    seeds = {step_seed(s, r, t) for s in range(3) for r in range(3) for t in range(0, 3000, 100)}
    assert len(seeds) == 3 * 3 * 30 and all(0 <= x < 2**63 for x in seeds)
    # the old shuffle seed, seed·1000 + epoch·10 + rank, gave seed 0 at epoch 100 seed 1's epoch 0
    assert shuffle_seed(0, 100, 0) != shuffle_seed(1, 0, 0) and 0 <= shuffle_seed(5, 7, 1) < 2**31


def test_non_finite_loss_stops_before_the_step_and_keeps_the_last_good_checkpoint(tmp_path):
    config = _config(tmp_path, steps=40, checkpoint_every=5)
    outcome = _run(config, toy_records(32), toy_spec(nan_at_call=13))
    assert outcome.status == "non_finite"
    assert outcome.step == 12  # steps 1..12 completed; the 13th forward gave NaN
    assert outcome.message.startswith("non-finite loss at step 13 (loss=nan")
    assert outcome.message.endswith("run stopped, its last good checkpoint is step 10")
    assert "\n" not in outcome.message
    latest = LocalSession(config, dataset=[]).store.latest()
    state = read_checkpoint_state(latest)
    assert state.step == 10 and all(math.isfinite(v) for v in state.metrics.values())
    assert max(r["step"] for r in read_metrics(config.metrics_path)) == 12


def test_too_few_records_for_one_batch_is_a_data_error(tmp_path):
    from core.errors import DataError

    with pytest.raises(DataError, match="not one full batch of 4 records"):
        _run(_config(tmp_path), toy_records(3))


def test_resume_refuses_a_run_dir_of_another_task(tmp_path):
    from services.training.checkpoints import CheckpointError

    _run(_config(tmp_path, steps=10), toy_records(8))
    with pytest.raises(CheckpointError, match="different run"):
        _run(_config(tmp_path, steps=20, task_options={"objective": "regression"}), toy_records(8))


def test_freeze_keeps_named_modules_fixed(tmp_path):
    from services.training.loop import TrainingError

    with pytest.raises(TrainingError, match="nothing to train"):
        _run(_config(tmp_path, steps=3, freeze=("head",)), toy_records(8))
    with pytest.raises(TrainingError, match="no module 'mapper'"):
        _run(_config(tmp_path, steps=3, freeze=("mapper",)), toy_records(8))


@pytest.mark.parametrize("precision, dtype", [("fp32", "float32"), ("bf16", "bfloat16")])
def test_precision_sets_the_forwards_autocast(tmp_path, precision, dtype):
    """--precision bf16 runs the task's forward under bfloat16 autocast (through the device's type), fp32
    without; the weights stay float32 either way. The config reaches Ray workers as to_dict/from_dict
    (services.training.job.ray_train_func), which keeps the field."""
    import torch

    from tests.unit.training.toy import ToyTask

    tasks = []

    def build(config, device):
        tasks.append(ToyTask().to(device))
        return tasks[-1]

    spec = toy_spec()
    spec = type(spec)(build=build, to_batch=spec.to_batch, exported=spec.exported)
    config = _config(tmp_path, steps=3, precision=precision)
    outcome = train_loop(config, LocalSession(config, dataset=toy_records(16)), spec)
    assert outcome.status == "finished" and outcome.step == 3
    assert tasks[0].pred_dtypes == [getattr(torch, dtype)] * 3
    assert tasks[0].head.weight.dtype == torch.float32
    assert TrainJobConfig.from_dict(config.to_dict()).precision == precision


def test_unknown_precision_is_a_config_error(tmp_path):
    from services.training.config import TrainConfigError

    with pytest.raises(TrainConfigError, match="--precision must be one of"):
        _config(tmp_path, precision="fp16")


def test_scalar_metrics_follow_the_loss_device():
    """A task may build a metric with torch.tensor(x) (CPU) while a CUDA run's loss is on the GPU; the loop
    stacks every scalar into one tensor, so each must land on the loss's device (the meta device stands in
    for CUDA here). Tensors of several elements are not metrics and are left out."""
    import torch

    from services.training.loop import _scalar_metrics

    out = {"loss": torch.zeros((), device="meta"), "acc": torch.tensor(0.5), "count": torch.tensor([3]),
           "map": torch.zeros(2, 2), "note": "not a tensor"}
    metrics = _scalar_metrics(out)
    assert sorted(metrics) == ["acc", "count", "loss"]
    assert all(v.device.type == "meta" and v.shape == () and v.dtype == torch.float32 for v in metrics.values())


def test_a_run_resumes_only_in_the_mode_that_started_it(tmp_path):
    # in-process and Ray runs keep their checkpoints in different folders and each mode resumes from its own:
    # continuing a run in the other mode would start again from step 0 beside the old checkpoints
    from services.training.job import TrainingError, _check_same_mode

    _run(_config(tmp_path, steps=10), toy_records(16))          # in-process: RUN_DIR/checkpoints
    _check_same_mode(_config(tmp_path, steps=20))              # the same mode resumes
    with pytest.raises(TrainingError, match=r"was started with --workers 0 \(in-process\)"):
        _check_same_mode(_config(tmp_path, steps=20, workers=1))
    (tmp_path / "run" / "checkpoints").rename(tmp_path / "run" / "ray_train")   # as a Ray run leaves it
    with pytest.raises(TrainingError, match=r"--workers >= 1 \(Ray Train\).*new --run-dir"):
        _check_same_mode(_config(tmp_path, steps=20))


def _stop_after(step_count: int, calls: list[int]):
    """A stop_requested that names SIGTERM from its `step_count`-th call on (the loop asks once per step)."""
    def stop_requested():
        calls.append(1)
        return "SIGTERM" if len(calls) >= step_count else None
    return stop_requested


@pytest.mark.parametrize("stop_at, checkpoints", [(7, [5, 7]), (10, [5, 10])])
def test_a_stop_request_saves_the_step_it_ends_on_and_a_rerun_resumes_there(tmp_path, stop_at, checkpoints):
    records = toy_records(32)
    config = _config(tmp_path, steps=20, checkpoint_every=5)
    calls: list[int] = []
    outcome = train_loop(config, LocalSession(config, dataset=records), toy_spec(),
                         stop_requested=_stop_after(stop_at, calls))
    assert outcome.status == "interrupted" and outcome.step == stop_at and len(calls) == stop_at
    assert "SIGTERM" in outcome.message and f"after step {stop_at} of 20" in outcome.message
    store = LocalSession(config, dataset=[]).store
    assert [read_checkpoint_state(p).step for p in store.list()] == checkpoints
    # batch 4 per step, 32 records: 8 batches an epoch; the stopped run is in epoch 0 (its first), at batch `stop_at`
    # of it or in the next epoch (numbered 1)
    assert read_checkpoint_state(store.latest()).data_position == divmod(stop_at, 8)
    assert math.isfinite(outcome.mean_metrics["loss"])
    again = _run(config, records)
    assert again.status == "finished" and again.start_step == stop_at and again.step == 20
    assert [r["step"] for r in read_metrics(config.metrics_path)] == list(range(1, 21))  # nothing repeated


@pytest.mark.parametrize("stop_at", [3, 8, 13])
def test_a_run_stopped_by_a_signal_and_resumed_trains_as_one_never_stopped(tmp_path, stop_at):
    # the same batches in the same order, the same random draws, the same optimizer and weight-average
    # state: the weights after 20 steps are bit for bit those of an uninterrupted run (stop_at 8 ends an epoch)
    import torch
    from safetensors.torch import load_file

    records = toy_records(32)
    whole_draws: list[float] = []
    whole = _config(tmp_path / "whole", steps=20, checkpoint_every=5, ema_decay=0.9)
    _run(whole, records, toy_spec(draws=whole_draws))
    cut_draws: list[float] = []
    cut = _config(tmp_path / "cut", steps=20, checkpoint_every=5, ema_decay=0.9)
    first = train_loop(cut, LocalSession(cut, dataset=records), toy_spec(draws=cut_draws),
                       stop_requested=_stop_after(stop_at, []))
    assert first.status == "interrupted" and first.step == stop_at
    _run(cut, records, toy_spec(draws=cut_draws))
    assert cut_draws == whole_draws
    losses = [[r["loss"] for r in read_metrics(c.metrics_path)] for c in (whole, cut)]
    assert losses[0] == losses[1]
    ends = [LocalSession(c, dataset=[]).store.latest() for c in (whole, cut)]
    for name in ("task.safetensors", "average.safetensors"):
        a, b = (load_file(str(d / name)) for d in ends)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name


@pytest.mark.parametrize("killed_at", [7, 9, 13])
def test_a_run_killed_without_a_word_resumes_from_its_last_checkpoint_on_the_same_batches(tmp_path, killed_at):
    """A kill (SIGKILL, out of memory, a lost machine) leaves no signal checkpoint: the rerun resumes from the
    last periodic one, which saved where the data stream stood, so the weights after 20 steps are bit for bit
    an uninterrupted run's (they were not: a resume there started an epoch of its own, other batches)."""
    import torch
    from safetensors.torch import load_file

    class Killed(Exception):
        pass

    def kill_at(step_count: int):
        calls = []

        def stop_requested():
            calls.append(1)
            if len(calls) >= step_count:
                raise Killed   # mid-run, after the step: nothing saved beyond the periodic checkpoints
            return None
        return stop_requested

    records = toy_records(32)
    whole = _config(tmp_path / "whole", steps=20, checkpoint_every=5, ema_decay=0.9)
    _run(whole, records)
    cut = _config(tmp_path / "cut", steps=20, checkpoint_every=5, ema_decay=0.9)
    with pytest.raises(Killed):
        train_loop(cut, LocalSession(cut, dataset=records), toy_spec(), stop_requested=kill_at(killed_at))
    store = LocalSession(cut, dataset=[]).store
    last = read_checkpoint_state(store.latest())
    assert last.step == killed_at // 5 * 5 and last.data_position == divmod(last.step, 8)   # 8 batches an epoch
    again = _run(cut, records)
    assert again.start_step == last.step and again.step == 20
    ends = [LocalSession(c, dataset=[]).store.latest() for c in (whole, cut)]
    assert read_checkpoint_state(ends[1]).data_position is None   # the last step's checkpoint keeps none
    for name in ("task.safetensors", "average.safetensors"):
        a, b = (load_file(str(d / name)) for d in ends)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name


def test_a_stop_request_at_the_first_step_saves_it_and_at_the_last_step_the_run_just_finishes(tmp_path):
    config = _config(tmp_path, steps=6, checkpoint_every=5)
    outcome = train_loop(config, LocalSession(config, dataset=toy_records(32)), toy_spec(),
                         stop_requested=lambda: "SIGINT")
    assert outcome.status == "interrupted" and outcome.step == 1
    assert [read_checkpoint_state(p).step for p in LocalSession(config, dataset=[]).store.list()] == [1]
    # resumed at 1, asked to stop at its 4th step: it stops at 5 (a periodic checkpoint, saved with the position) ...
    outcome = train_loop(config, LocalSession(config, dataset=toy_records(32)), toy_spec(),
                         stop_requested=_stop_after(4, []))
    assert outcome.status == "interrupted" and (outcome.start_step, outcome.step) == (1, 5)
    # ... and a run whose next step is its last finishes: there is nothing left to resume
    outcome = train_loop(config, LocalSession(config, dataset=toy_records(32)), toy_spec(),
                         stop_requested=lambda: "SIGINT")
    assert outcome.status == "finished" and (outcome.start_step, outcome.step) == (5, 6)
