"""The training loop every worker runs: one plain-PyTorch step of a `core` task, repeated.

`train_loop(config, session)` is the same code for the in-process mode (workers=0) and for each Ray
Train worker; the `session` (services/training/sessions.py) hides where batches come from, where
checkpoints go, and how values are averaged over workers.

Guarantees:
- resume: the session's latest checkpoint (if any) restores task, optimizer, step and weight average;
  otherwise an `--init` bundle's modules are loaded; the loop then runs until `config.steps`. Torch's
  generators are seeded before every step from (run seed, rank, step) (seeding.py), so a task's random
  draws at a step do not depend on where the run was cut (its batch order does; a task built with its
  own `seed` option keeps its own generator, which a resume restarts).
- `config.ema_decay > 0`: a moving average of the weights (weight_average.py) follows every optimizer
  step and goes into each checkpoint; the export and the benchmark's held-out criterion read it.
- every `checkpoint_every` steps and at the last step every rank calls `session.report` (a Ray
  collective) and rank 0 attaches a checkpoint.
- a non-finite loss or gradient norm stops every rank before the optimizer step and before any
  checkpoint of that step, so the newest checkpoint is the last good one; the loop returns a
  `LoopOutcome` with status "non_finite" and a one-line message.
- in-process runs only: once `stop_requested()` names a signal (services/training/stop_signal.py: the
  first Ctrl-C or SIGTERM), the loop saves a checkpoint at the step it just finished, with the data
  stream's position (epoch, batches of it done), and returns status "interrupted"; a rerun resumes at
  that step and batch, so a stopped and resumed run trains exactly as one never stopped. (A resume from a
  periodic checkpoint starts a fresh epoch, numbered by its step.)
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import asdict, dataclass, field
from typing import Callable, Protocol

import torch

from core.errors import DataError, N3dmapError
from services.malloc import keep_heap
from services.training.checkpoints import (
    check_same_run, load_checkpoint, read_checkpoint_state, save_checkpoint,
)
from services.training.config import TrainJobConfig
from services.training.progress import ProgressLogger
from services.training.seeding import step_seed
from services.training.stop_signal import never
from services.training.weight_average import WeightAverage


class TrainingError(N3dmapError):
    """A run stopped on purpose (non-finite loss, data too small): the message says why."""


class TrainingInterrupted(KeyboardInterrupt):
    """An in-process run stopped by a signal between two steps, its checkpoint saved (stop_signal.py); the
    message says at which step and how to resume. A KeyboardInterrupt, as the signal would have raised:
    clean-ups that catch Exception let it through, and the CLI reports it as an interruption (exit 130)."""


@dataclass(frozen=True)
class TaskSpec:
    """How the loop builds a task and turns records into its batch (injectable for tests).

    build(config, device) -> nn.Module with forward(batch) -> {"loss": scalar, other scalars...}
    to_batch(records: list[dict], device) -> batch dict of tensors
    exported(task) -> dict[str, nn.Module] (the modules an --init bundle fills and --freeze names)
    """

    build: Callable
    to_batch: Callable
    exported: Callable


def _core_build(config: TrainJobConfig, device: torch.device) -> torch.nn.Module:
    from core.presets import get_preset
    from core.tasks import build_task

    return build_task(config.task, get_preset(config.preset), **config.task_options).to(device)


def _core_to_batch(records: list[dict], device: torch.device) -> dict:
    from core.data.batch import records_to_batch

    batch = records_to_batch(records, device)
    # contiguous(): rgb arrives as a permuted (channels-last) view, and torch 2.13's oneDNN backward
    # of a strided 1×1 conv on such an input corrupts the heap (double free; seen in Net2D's shortcut).
    return {k: v.contiguous() for k, v in batch.items()}


def _core_exported(task: torch.nn.Module) -> dict:
    return task.exported_modules()


CORE_TASKS = TaskSpec(build=_core_build, to_batch=_core_to_batch, exported=_core_exported)


class TrainSession(Protocol):
    """Where the loop runs. See sessions.py for the in-process and Ray Train versions."""

    rank: int
    world_size: int
    device: torch.device
    progress_stream: object  # where rank 0 prints progress lines (None: only metrics.jsonl)
    # Whether epoch_batches can start part way into an epoch (`skip`): then every checkpoint before the last
    # step saves where the data stream stood, so a resume from it after a kill (no signal, no final save)
    # trains on the same batches as the run would have. Ray Train's streamed shards cannot skip.
    skips_into_epochs: bool

    def epoch_batches(self, epoch: int, skip: int = 0):
        """Yield lists of `batch_size` records (dicts of numpy arrays) for this worker's share, from the
        `skip`-th batch of the epoch on (in-process only: a resume after a signal)."""

    def latest_checkpoint(self):
        """Context manager yielding the newest checkpoint directory of the run, or None."""

    def staging_dir(self, step: int):
        """A fresh directory rank 0 writes a checkpoint into before `report`."""

    def report(self, metrics: dict, step: int, checkpoint_dir) -> None:
        """Collective: every rank calls it; rank 0 passes its staged checkpoint dir."""

    def prepare_model(self, model: torch.nn.Module) -> torch.nn.Module:
        """Wrap for data parallelism (DDP) where there are several workers."""

    def all_reduce_mean(self, values: torch.Tensor) -> torch.Tensor:
        """Mean of a 1-D tensor over workers (identity for one worker)."""


@dataclass
class LoopOutcome:
    """What the loop returns (rank 0's value becomes Ray's Result.return_value)."""

    status: str                      # "finished" | "non_finite" | "error" | "interrupted"
    step: int                        # last completed step
    start_step: int                  # step the run (re)started from
    message: str = ""
    last_metrics: dict = field(default_factory=dict)
    mean_metrics: dict = field(default_factory=dict)   # mean over the steps of this attempt

    def to_dict(self) -> dict:
        return asdict(self)


def freeze_modules(task: torch.nn.Module, exported: dict[str, torch.nn.Module], names) -> None:
    """Stop gradients to the named exported modules (their BatchNorm stats stay fixed too)."""
    for name in names:
        if name not in exported:
            raise TrainingError(f"--freeze {name}: the task has no module {name!r} "
                                f"(it has {sorted(exported)})")
        exported[name].requires_grad_(False)


def _set_train_mode(task: torch.nn.Module, exported: dict, frozen) -> None:
    task.train()
    for name in frozen:
        exported[name].eval()  # frozen features: keep BatchNorm running stats as loaded


def load_init_bundle(exported: dict[str, torch.nn.Module], bundle_dir: str, *, preset_name: str,
                     device: torch.device) -> list[str]:
    """Copy the weights of the bundle's modules into the task's modules of the same name; returns
    the names copied (possibly none)."""
    from core.bundle import load_bundle

    bundle = load_bundle(bundle_dir, device)
    bundle_preset = getattr(bundle.preset, "name", bundle.preset)
    if bundle_preset != preset_name:
        raise TrainingError(f"--init {bundle_dir}: bundle preset {bundle_preset!r} does not match "
                            f"--preset {preset_name!r}")
    loaded = []
    for name, module in bundle.modules.items():
        if name in exported:
            try:
                exported[name].load_state_dict(module.state_dict())
            except RuntimeError as e:
                detail = next((line.strip() for line in str(e).splitlines() if "mismatch" in line
                               or "Missing" in line or "Unexpected" in line), "incompatible weights")
                raise TrainingError(f"--init {bundle_dir}: module {name!r} does not fit this task "
                                    f"({detail})") from None
            loaded.append(name)
    # A task may share no module with its init bundle (egomotion learns its own encoder): then
    # nothing is warm-started, and the bundle's modules are still carried into the export.
    return sorted(loaded)


def _scalar_metrics(out: dict) -> dict[str, torch.Tensor]:
    if "loss" not in out:
        raise TrainingError(f"task forward returned no 'loss' (keys: {sorted(out)})")
    # Every scalar onto the loss's device: the loop stacks them into one tensor (one all-reduce), and a
    # task that builds a metric with torch.tensor(x) leaves it on the CPU while a CUDA run's loss is not.
    device = out["loss"].device
    return {k: v.detach().float().reshape(()).to(device) for k, v in out.items()
            if isinstance(v, torch.Tensor) and v.numel() == 1}


def _format_bad(values: dict[str, float]) -> str:
    return ", ".join(f"{k}={v}" for k, v in values.items() if not math.isfinite(v)) or "?"


def train_loop(config: TrainJobConfig, session: TrainSession, spec: TaskSpec = CORE_TASKS, *,
               stop_requested: Callable[[], str | None] = never) -> LoopOutcome:
    """Run (or resume) the training of `config` on this worker; see the module docstring.
    stop_requested: in-process runs only (every rank would have to agree): the name of the signal that
    asked the run to stop, or None."""
    keep_heap()  # services.malloc: each step's large tensors reuse the heap instead of fresh mmaps (Ray workers too)
    torch.manual_seed(config.seed)  # identical initial weights on every rank (DDP also broadcasts)
    device = session.device
    task = spec.build(config, device)
    exported = spec.exported(task)
    freeze_modules(task, exported, config.freeze)

    trainable = [p for p in task.parameters() if p.requires_grad]
    if not trainable:
        raise TrainingError("nothing to train: every parameter of the task is frozen")
    optimizer = torch.optim.Adam(trainable, lr=config.lr)

    start_step = 0
    position = None
    average = None
    with session.latest_checkpoint() as ckpt_dir:
        if ckpt_dir is None and config.init_bundle:
            load_init_bundle(exported, config.init_bundle, preset_name=config.preset, device=device)
        if config.ema_decay:
            average = WeightAverage(task, decay=config.ema_decay)  # starts at the initial (or --init) weights
        if ckpt_dir is not None:
            state = read_checkpoint_state(ckpt_dir)
            check_same_run(state.config, config.identity(), ckpt_dir)
            state = load_checkpoint(ckpt_dir, task=task, optimizer=optimizer, average=average)
            start_step, position = state.step, state.data_position

    model = session.prepare_model(task)
    logger = None
    if session.rank == 0:
        logger = ProgressLogger(metrics_path=config.metrics_path, total_steps=config.steps,
                                start_step=start_step, stream=session.progress_stream)
        if start_step:
            print(f"resuming {config.task} from step {start_step} ({config.run_dir})", flush=True)

    step = start_step
    saved_step = start_step  # the newest checkpoint of the run (0: none yet)
    names: list[str] | None = None
    sums: torch.Tensor | None = None
    last: dict[str, float] = {}
    # A resumed run starts at an epoch index of its own (the step it resumes from), so its shuffles differ
    # from the ones before the cut: a run trained in chunks (the benchmark's held-out stopping rule)
    # would otherwise replay the first epochs' batch order at the start of every chunk. A run stopped by a
    # signal saved where its data stream stood instead, and goes on from there (skip: batches already done).
    epoch, skip = position if position is not None else (start_step, 0)
    while step < config.steps:
        batches_this_epoch = skip
        for records in session.epoch_batches(epoch, skip):
            batches_this_epoch += 1
            torch.manual_seed(step_seed(config.seed, session.rank, step))  # draws by step, not by call (seeding.py)
            _set_train_mode(task, exported, config.freeze)
            batch = spec.to_batch(records, device)
            # bf16: autocast (CPU or CUDA, from the device) covers the forward and the task's loss; the
            # backward follows the forward's dtypes, and the optimizer updates the float32 weights.
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=config.precision == "bf16"):
                out = model(batch)
            metrics = _scalar_metrics(out)
            if names is None:
                names = sorted(metrics)
            # Average over workers first, so every rank takes the same stop decision.
            reduced = session.all_reduce_mean(torch.stack([metrics[k] for k in names]))
            values = dict(zip(names, reduced.tolist()))
            if not all(math.isfinite(v) for v in values.values()):
                return _stopped(step, start_step, saved_step, values, f"non-finite loss at step "
                                f"{step + 1} ({_format_bad(values)})", sums, names)

            optimizer.zero_grad(set_to_none=True)
            out["loss"].backward()
            max_norm = config.grad_clip if config.grad_clip > 0 else float("inf")
            grad_norm = torch.nn.utils.clip_grad_norm_(trainable, max_norm)
            if not torch.isfinite(grad_norm):  # DDP all-reduced the grads: the same on every rank
                return _stopped(step, start_step, saved_step, values, f"non-finite gradient norm at step "
                                f"{step + 1} (loss={values['loss']:.4g})", sums, names)
            optimizer.step()
            step += 1
            if average is not None:
                average.update(task, step=step)
            last = values
            sums = reduced.cpu() if sums is None else sums + reduced.cpu()

            if logger is not None and (step % config.log_every == 0 or step == config.steps
                                       or step == start_step + 1):
                logger.log(step, values)
            _maybe_inject_fault(config, session, step)
            if step % config.checkpoint_every == 0 or step == config.steps:
                # The last step's checkpoint keeps none: a run trained in chunks (the benchmark's plateau rule)
                # starts each chunk at an epoch of its own (above), as it always has.
                position = ((epoch, batches_this_epoch) if session.skips_into_epochs and step < config.steps
                            else None)
                _report_checkpoint(config, session, task, optimizer, step, values, average, data_position=position)
                saved_step = step
            if step >= config.steps:
                break
            why = stop_requested()
            if why is not None:  # saved again with the data position, even where the step's checkpoint exists
                _report_checkpoint(config, session, task, optimizer, step, values, average,
                                   data_position=(epoch, batches_this_epoch))
                return LoopOutcome(status="interrupted", step=step, start_step=start_step, last_metrics=last,
                                   mean_metrics=_mean_metrics(names, sums, step - start_step), message=f"stopped by {why} after step {step} of "
                                   f"{config.steps}; its checkpoint is saved in {config.run_dir}: rerun the same "
                                   f"command to resume there")
        if batches_this_epoch == 0:
            raise DataError(f"{config.data_dir}: not one full batch of {config.batch_size} records "
                            f"per worker ({session.world_size} worker(s)); use a smaller "
                            f"--batch-size, fewer --workers or a bigger dataset")
        epoch += 1
        skip = 0

    return LoopOutcome(status="finished", step=step, start_step=start_step, last_metrics=last,
                       mean_metrics=_mean_metrics(names, sums, step - start_step))


def _mean_metrics(names: list[str] | None, sums: torch.Tensor | None, steps: int) -> dict[str, float]:
    """Each metric's mean over the `steps` steps of this attempt ({} when none ran)."""
    if sums is None or steps <= 0:
        return {}
    return {k: v / steps for k, v in zip(names or [], sums.tolist())}


def _stopped(step, start_step, saved_step, values, message, sums, names) -> LoopOutcome:
    last_good = (f"; run stopped, its last good checkpoint is step {saved_step}" if saved_step
                 else "; run stopped before its first checkpoint")
    return LoopOutcome(status="non_finite", step=step, start_step=start_step,
                       message=message + last_good, last_metrics=values,
                       mean_metrics=_mean_metrics(names, sums, step - start_step))


def _report_checkpoint(config, session, task, optimizer, step, values, average, data_position=None) -> None:
    staged = None
    if session.rank == 0:
        staged = session.staging_dir(step)
        save_checkpoint(staged, task=task, optimizer=optimizer, step=step, config=config.to_dict(),
                        metrics=values, average=average, data_position=data_position)
    try:
        session.report({"step": step, **values}, step, staged)
    finally:
        if staged is not None and os.path.isdir(staged):
            shutil.rmtree(staged, ignore_errors=True)


def _maybe_inject_fault(config: TrainJobConfig, session, step: int) -> None:
    """Test hook: the rank-0 process dies hard once, at `fault_at_step`, on the first attempt."""
    if config.fault_at_step is None or step != config.fault_at_step or session.rank != 0:
        return
    marker = config.fault_marker_path
    if marker.exists():
        return
    marker.parent.mkdir(parents=True, exist_ok=True)
    marker.write_text(f"worker process {os.getpid()} exited on purpose at step {step}\n")
    print(f"fault injection: worker exits at step {step}", flush=True)
    os._exit(17)
