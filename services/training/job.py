"""Run one training job: in this process (workers=0) or as a Ray Train `TorchTrainer`, then export.

`run_training(config)` is what `n3dmap train <task>` calls when no `--address` is given:

- workers=0: the loop runs right here (no Ray), checkpoints under RUN_DIR/checkpoints/. The first Ctrl-C or
  SIGTERM stops it after the step under way, with a checkpoint there (services/training/stop_signal.py),
  and raises TrainingInterrupted; a rerun resumes at that step.
- workers>=1: an embedded local Ray (one logical CPU more than the workers: Ray Data's read tasks
  need one, see docs/ecosystem.md#ray) — or, with `config.attach`, the Ray cluster this process runs in (a
  Ray Jobs entrypoint) — runs `TorchTrainer` with a Ray Data stream of the shards split over the
  workers, DDP, `FailureConfig(max_failures)`, and checkpoints under RUN_DIR/ray_train/. The same
  RunConfig(name, storage_path) on a rerun makes Ray hand the latest checkpoint back: that is resume. The first
  Ctrl-C or SIGTERM ends the worker group (Ray is shut down; fit() runs off the main thread so that Ray's own
  SIGINT handler, which reported an aborted run as success, is never installed) and raises TrainingInterrupted
  naming the last periodic checkpoint, where a rerun resumes.

A finished run exports RUN_DIR/bundle/ (core.bundle.save_bundle) from its final checkpoint: the
weight average's weights where the run keeps one (--ema-decay), else the last step's.
"""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import torch

from core.data.shards import dataset_shard_paths
from core.errors import DataError, N3dmapError
from services.training.checkpoints import (
    LocalCheckpointStore, check_same_run, is_complete, load_checkpoint, read_checkpoint_state,
)
from services.training.config import TrainJobConfig
from services.training.progress import MetricsTail
from services.training.loop import (
    CORE_TASKS, LoopOutcome, TaskSpec, TrainingError, TrainingInterrupted, train_loop,
)
from services.training.stop_signal import graceful_stop, never

PROJECT_ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class RunSummary:
    """What a finished run produced."""

    run_dir: Path
    bundle_dir: Path
    checkpoint_dir: Path
    outcome: LoopOutcome
    seconds: float


def check_dataset(config: TrainJobConfig) -> dict:
    """The dataset's manifest; DataError if it is missing/corrupt or made for another preset."""
    _, _, manifest = dataset_shard_paths(config.data_dir)
    data_preset = manifest.get("preset")
    if data_preset is not None and data_preset != config.preset:
        raise DataError(f"dataset {config.data_dir} was made with preset {data_preset!r}, "
                        f"but the run uses --preset {config.preset!r}")
    needed = max(1, config.workers) * config.batch_size
    if manifest["num_records"] < needed:
        raise DataError(f"dataset {config.data_dir} has {manifest['num_records']} records; one step of "
                        f"{max(1, config.workers)} worker(s) × --batch-size {config.batch_size} needs {needed}")
    return manifest


def run_training(config: TrainJobConfig, *, spec: TaskSpec = CORE_TASKS) -> RunSummary:
    """Train (or resume) `config` to its last step and export its bundle; see the module docstring."""
    config = config.resolved()
    manifest = check_dataset(config)
    config.run_path.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    # The first Ctrl-C / SIGTERM stops the run (stop_signal.py): in-process between two steps, with a checkpoint
    # at that step; on Ray by ending the worker group (its last periodic checkpoint is where a rerun resumes).
    # One that comes during the last step, the final checkpoint or the export still stops the caller once the
    # bundle is written, rather than being lost when the handlers are restored.
    with graceful_stop() as stop_requested:
        done = _finished_checkpoint(config)
        if done is not None:  # rerun of a complete run: nothing to train, export again
            checkpoint_dir, state = done
            outcome = LoopOutcome(status="finished", step=state.step, start_step=state.step,
                                  last_metrics=state.metrics)
        else:
            _check_same_mode(config)
            outcome, checkpoint_dir = (_run_in_process(config, spec, stop_requested) if config.workers == 0
                                       else _run_on_ray(config, stop_requested))
        if outcome.status == "interrupted":
            raise TrainingInterrupted(outcome.message)
        if outcome.status != "finished":
            raise TrainingError(outcome.message)
        if checkpoint_dir is None:  # nothing trained this time (already at --steps): use the newest
            checkpoint_dir = latest_checkpoint_dir(config)
        if checkpoint_dir is None:
            raise TrainingError(f"run {config.run_dir} finished but left no checkpoint")
        bundle_dir = export_bundle(config, checkpoint_dir, outcome=outcome, manifest=manifest, spec=spec)
        late = stop_requested()
    if late is not None:
        raise TrainingInterrupted(f"stopped by {late} as the run ended: it finished (step {outcome.step} of "
                                  f"{config.steps}) and its bundle is exported to {bundle_dir}")
    return RunSummary(run_dir=config.run_path, bundle_dir=bundle_dir, checkpoint_dir=Path(checkpoint_dir),
                      outcome=outcome, seconds=time.monotonic() - started)


def _finished_checkpoint(config: TrainJobConfig):
    """(dir, state) of the run's newest checkpoint if it already reached config.steps, else None."""
    latest = latest_checkpoint_dir(config)
    if latest is None:
        return None
    state = read_checkpoint_state(latest)
    check_same_run(state.config, config.identity(), latest)
    return (latest, state) if state.step >= config.steps else None


def _check_same_mode(config: TrainJobConfig) -> None:
    """A run resumes only in the mode that started it: in-process runs (--workers 0) keep their
    checkpoints under RUN_DIR/checkpoints and Ray runs under RUN_DIR/<ray storage>, and each mode resumes
    from its own folder only — a cut-off Ray run continued in-process would start again from step 0 while
    its evaluations and newest checkpoint stayed beside it. TrainingError naming both, if so."""
    # the other mode's folder
    there = config.run_path / config.ray_storage_name if config.workers == 0 else config.local_checkpoint_root
    if LocalCheckpointStore(there, keep=1).list():
        other = "--workers 0 (in-process)" if config.workers > 0 else "--workers >= 1 (Ray Train)"
        raise TrainingError(f"run {config.run_dir} was started with {other} (checkpoints in {there}); "
                            f"resume it that way, or use a new --run-dir")


# ----------------------------------------------------------------------------- in-process

def _run_in_process(config: TrainJobConfig, spec: TaskSpec,
                    stop_requested: Callable[[], str | None]) -> tuple[LoopOutcome, Path | None]:
    from services.training.sessions import LocalSession

    session = LocalSession(config)
    outcome = train_loop(config, session, spec, stop_requested=stop_requested)
    return outcome, session.store.latest()


# ----------------------------------------------------------------------------- Ray Train

def ray_train_func(loop_config: dict) -> dict:
    """The `train_loop_per_worker` of the TorchTrainer: rebuild the config, run the shared loop."""
    from services.training.sessions import RaySession

    torch.set_num_threads(max(1, int(loop_config.get("threads", 1))))
    config = TrainJobConfig.from_dict(loop_config["config"])
    try:
        return train_loop(config, RaySession(config)).to_dict()
    except DataError:
        # A bad record reaches one rank only (each decodes its own split of the stream): raised, it fails the
        # worker group at once and its message ends the run (after Ray's --max-failures retries, which meet the
        # record again). Returned as an error outcome, it ended this rank alone while the others waited in their
        # next collective until gloo's 30-minute timeout, per attempt.
        raise
    except N3dmapError as e:
        # Bad options / checkpoint: the same on every rank and on every retry, so end the run with the message
        # instead of raising (Ray would restart the workers max_failures times).
        return LoopOutcome(status="error", step=-1, start_step=-1, message=str(e)).to_dict()


def embedded_ray_defaults() -> None:
    """The embedded Ray reports no usage statistics unless the user opted in (RAY_USAGE_STATS_ENABLED=1 set
    before the run): it is a private, throw-away cluster on the user's machine, and n3dmap keeps the Rerun
    viewer's analytics off by the same rule (README, "3D viewer (Rerun)"). Ray reads the variable when its
    head starts, inside `ray.init`."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


def _init_ray(config: TrainJobConfig) -> bool:
    """Start an embedded Ray (or attach to the surrounding cluster). Returns True if we started one."""
    import ray

    if ray.is_initialized():
        return False
    if config.attach:
        # Inside a Ray Jobs entrypoint: join that cluster (RAY_ADDRESS is set by the job supervisor).
        # No runtime_env here: the job's own (its uploaded working_dir) must reach every node.
        _keeping_sigterm(lambda: ray.init(address="auto", log_to_driver=False))
        return True
    embedded_ray_defaults()
    # Workers import `core`/`services` from this checkout even when n3dmap is not pip-installed.
    pythonpath = os.pathsep.join(p for p in (str(PROJECT_ROOT), os.environ.get("PYTHONPATH")) if p)
    runtime_env = {"env_vars": {"PYTHONPATH": pythonpath}}
    gpus = int(round(config.workers * config.gpus_per_worker + 0.499)) if config.gpus_per_worker else 0
    _keeping_sigterm(lambda: ray.init(
        address="local",
        num_cpus=config.workers * config.cpus_per_worker + 1,  # +1: Ray Data read tasks need a CPU
        num_gpus=gpus or None,
        include_dashboard=False,
        object_store_memory=config.object_store_mb * 2**20,
        runtime_env=runtime_env,
        # Workers' own logs (Ray Data bars, Train internals) stay in Ray's log files; the console
        # gets the progress lines the driver reads back from metrics.jsonl (MetricsTail).
        log_to_driver=False,
        configure_logging=True,
        logging_level="WARNING",
    ))
    return True


def _keeping_sigterm(init: Callable[[], object]) -> None:
    """Run `init` (ray.init) and put back the SIGTERM handler it replaces: on the main thread ray.init installs
    one that calls sys.exit, which took SIGTERM from graceful_stop (the run exited 15 with no word)."""
    if threading.current_thread() is not threading.main_thread():
        init()
        return
    previous = signal.getsignal(signal.SIGTERM)
    try:
        init()
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run_on_ray(config: TrainJobConfig, stop_requested: Callable[[], str | None] = never
                ) -> tuple[LoopOutcome, Path | None]:
    import ray
    import ray.data
    from ray.train import CheckpointConfig, FailureConfig, RunConfig, ScalingConfig
    from ray.train.torch import TorchTrainer

    from services.training.data import read_shards

    os.environ.setdefault("RAY_TRAIN_V2_ENABLED", "1")
    started_here = _init_ray(config)
    stopped = False
    ray.data.DataContext.get_current().enable_progress_bars = False
    try:
        resources = {"CPU": config.cpus_per_worker}
        if config.gpus_per_worker:
            resources["GPU"] = config.gpus_per_worker
        threads = worker_threads(config)
        trainer = TorchTrainer(
            ray_train_func,
            train_loop_config={"config": config.to_dict(), "threads": threads},
            scaling_config=ScalingConfig(num_workers=config.workers, use_gpu=config.gpus_per_worker > 0,
                                         resources_per_worker=resources),
            run_config=RunConfig(
                name=config.ray_storage_name, storage_path=config.run_dir,
                checkpoint_config=CheckpointConfig(num_to_keep=config.keep_checkpoints),
                failure_config=FailureConfig(max_failures=config.max_failures),
            ),
            datasets={"train": read_shards(config.data_dir, seed=config.seed)},
        )
        tail = MetricsTail(config.metrics_path).run_in_thread()
        try:
            result = _fit_until_stopped(trainer, stop_requested)
        except Exception as e:  # TrainingFailedError wraps the worker's exception
            raise TrainingError(_root_cause_line(e)) from None
        finally:
            tail.stop()
        if result is None:   # a stop was requested: shutting Ray down ends the workers (attached runs too: the
            stopped = True   # run's controller is this driver's), and only then is the last checkpoint known
            ray.shutdown()
            latest = latest_checkpoint_dir(config)
            where = (f"its last checkpoint is at step {read_checkpoint_state(latest).step} ({latest})" if latest
                     else "it had saved no checkpoint yet")
            raise TrainingInterrupted(f"stopped by {stop_requested()}: the Ray run is ended; {where}, and the "
                                      "same command resumes from it")
        outcome = LoopOutcome(**result.return_value)
        checkpoint = result.checkpoint
        return outcome, Path(checkpoint.path) if checkpoint is not None else None
    finally:
        if started_here and not stopped:
            ray.shutdown()


def _earlier_means(bundle_dir: Path) -> dict[str, float]:
    """The mean_* metrics of the bundle an earlier export wrote to `bundle_dir` ({} when there is none)."""
    from core.bundle import read_bundle_meta
    from core.errors import BundleError

    try:
        earlier = read_bundle_meta(bundle_dir).get("metrics", {})
    except (BundleError, OSError):
        return {}
    return {k: float(v) for k, v in earlier.items() if k.startswith("mean_") and isinstance(v, (int, float))}


def _fit_until_stopped(trainer, stop_requested: Callable[[], str | None]):
    """trainer.fit()'s result, or None once `stop_requested()` says a signal asked to stop.

    fit() runs on a thread of its own: on the main thread it installs Ray's own SIGINT handler, which aborts the
    run and may end the process with sys.exit(0) (a Ctrl-C'd run reported success, exit 0) and stays installed
    after fit returns (a later Ctrl-C started a fresh local Ray inside the handler). Off the main thread it installs
    none, and the signals stay with graceful_stop. The thread is a daemon: once Ray is shut down its fit() ends
    with an error or not at all, and neither may hold the process."""
    box: dict = {}

    def fit() -> None:
        try:
            box["result"] = trainer.fit()
        except BaseException as e:  # handed to the caller's thread
            box["error"] = e

    thread = threading.Thread(target=fit, name="n3dmap-ray-fit", daemon=True)
    thread.start()
    while thread.is_alive():
        thread.join(0.2)
        if thread.is_alive() and stop_requested() is not None:   # finished meanwhile: its result stands
            return None
    if "error" in box:
        raise box["error"]
    return box["result"]


def worker_threads(config: TrainJobConfig) -> int:
    """Torch threads of each Ray Train worker. On the embedded local Ray the workers share this machine:
    its usable CPUs are shared out (processes × threads ≤ CPUs; more workers than CPUs get one thread
    each and the plan, printed, says it is oversubscribed). On a cluster (attach) each worker gets the
    CPUs Ray reserved for it."""
    if config.attach:
        return config.cpus_per_worker
    from services.threads import plan_threads

    plan = plan_threads(processes=config.workers, cap_processes=False)
    print(f"threads: {plan.describe()}", flush=True)
    return plan.threads


def _root_cause_line(error: BaseException) -> str:
    """One line for a failed Ray Train run: the innermost worker error, without the traceback."""
    seen = set()
    cause = error
    while True:
        nxt = getattr(cause, "worker_failures", None)
        if isinstance(nxt, dict) and nxt:
            cause = next(iter(nxt.values()))
            continue
        nxt = cause.__cause__ or getattr(cause, "cause", None)
        if nxt is None or id(nxt) in seen:
            break
        seen.add(id(nxt))
        cause = nxt
    text = str(cause).strip().splitlines()
    # Ray prefixes worker errors with a traceback dump; the last line is the exception itself.
    line = text[-1] if text else type(cause).__name__
    return f"training failed: {line}"


# ----------------------------------------------------------------------------- bundle export

def export_bundle(config: TrainJobConfig, checkpoint_dir: str | Path, *, outcome: LoopOutcome,
                  manifest: dict, spec: TaskSpec = CORE_TASKS) -> Path:
    """Write RUN_DIR/bundle/ from the final checkpoint (plus any --init modules the task lacks)."""
    from core.bundle import load_bundle, merged_modules, parent_provenance, save_bundle
    from core.presets import get_preset

    device = torch.device("cpu")
    task = spec.build(config, device)
    state = load_checkpoint(checkpoint_dir, task=task, averaged_weights=True)  # the average, if the run kept one
    modules = dict(spec.exported(task))
    parents = []
    if config.init_bundle:
        # Keep what the init bundle had (e.g. the pretrained projector) next to what this task trained;
        # modules of the same name come from this run (fine-tuned or copied-then-frozen).
        parent = load_bundle(config.init_bundle, device)
        modules = merged_modules(parent, modules, replace=True)
        parents.append(parent_provenance(parent))
    last = outcome.last_metrics or state.metrics
    metrics = {f"last_{k}": float(v) for k, v in last.items()}
    if outcome.mean_metrics:
        # over this attempt's steps only: a resumed run's means start where it resumed, and say so
        metrics.update({f"mean_{k}": float(v) for k, v in outcome.mean_metrics.items()})
        metrics["mean_from_step"] = float(outcome.start_step + 1)
    else:   # a rerun of a finished run trains nothing: its bundle keeps the means its export had
        metrics.update(_earlier_means(config.bundle_path))
    save_bundle(config.bundle_path, modules=modules, preset=get_preset(config.preset),
                provenance=run_provenance(config, manifest=manifest, steps=state.step, parents=parents),
                metrics=metrics)
    return config.bundle_path


def run_provenance(config: TrainJobConfig, *, manifest: dict, steps: int, parents: list[dict]) -> dict:
    """The provenance a run's bundle records: the task and its options at the top level, the data, the
    run's settings, and `parents` (core.bundle.parent_provenance of the --init bundle, which nests its
    own parents: services/cli/lineage.py prints the chain)."""
    return {
        "task": config.task,
        **{k: v for k, v in config.task_options.items()},
        "data_manifest": str(Path(config.data_dir) / "manifest.json"),
        "data_seed": manifest.get("seed"),
        "data_split": manifest.get("split"),
        "steps": steps,
        "workers": config.workers,
        "batch_size_per_worker": config.batch_size,
        "lr": config.lr,
        "seed": config.seed,
        "precision": config.precision,
        "ema_decay": config.ema_decay,
        "init_bundle": config.init_bundle,
        "frozen": list(config.freeze),
        "git_commit": git_commit(),
        "run_dir": config.run_dir,
        "run_id": config.run_path.name,
        "parents": parents,
    }


def git_commit() -> str | None:
    """HEAD of the source tree this code runs from, if it is a git checkout."""
    try:
        out = subprocess.run(["git", "-C", str(PROJECT_ROOT), "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def latest_checkpoint_dir(config: TrainJobConfig) -> Path | None:
    """The newest complete checkpoint of a run dir, whichever mode wrote it: one cut short (a Ray copy stopped part
    way, a torn state.json) is passed over, as the workers pass over it when they resume, so that the driver
    neither exports it nor fails on it."""
    config = config.resolved()
    candidates = [p for root in (config.local_checkpoint_root, config.run_path / config.ray_storage_name)
                  for p in LocalCheckpointStore(root, keep=1).list() if is_complete(p)]
    if not candidates:
        return None
    return max(candidates, key=lambda p: read_checkpoint_state(p).step)
