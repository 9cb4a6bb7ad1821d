"""`n3dmap bench paper`: reproduce the paper's tables and figures on the synthetic world, end to end.

`run_paper_bench(config, out_dir)` runs, as resumable stages under OUT/work/ (services.bench.stages):

  data/train, data/val, data/test       synthetic datasets (services.bench.data); val feeds the stopping
                                        rules, test every evaluation
  seed<s>/pretrain_<arm>                view-contrastive and view-regression pretraining
  seed<s>/occupancy_contrastive         the occupancy module by the paper's protocol (one input view, labels
                                        from it and one other view), fine-tuned from the contrastive pretraining
  seed<s>/detector_<arm>_<mode>_L<N>    detector per arm (random/regression/contrastive), frozen or
                                        fine-tuned features, per label budget (trained on the first N
                                        records, RUN_DIR/labelled_data, as `train detector --labels N`)
  seed<s>/detector_..._L<N>_draw<d>     the smallest budget's further label draws (records [d·N, (d+1)·N);
                                        plan.label_draws); its detection rows are the mean over the draws
  seed<s>/flow_<arm>                    3D flow over the frozen features of each pretrained arm
  seed<s>/flow_volume                   3D flow over the fused input volumes (n3dmap's default)
  seed<s>/egomotion                     the egomotion module
  seed<s>/eval/<kind>/<name>            one metrics.json per evaluation (detection mAP, retrieval,
                                        occupancy, flow EPE, egomotion vs ICP, moving objects)

(one seed's stages, in order: services.bench.seed_stages), then writes OUT/report.md, OUT/metrics.json and
the PNG plots (services.bench.report). Each training
stage trains by its stopping rule (services.bench.stopping) and keeps RUN_DIR/stopping.json. Seeds run
one after another in this process with every CPU, or `parallel_seeds` at a time in worker processes
(services.bench.seed_worker) with the CPUs shared out (services.threads): processes × threads never
exceeds the usable CPUs. Training goes
through the training CLI's own job runner (services.bench.training); every evaluation is scored by the
protocols `n3dmap eval` runs (core.eval.protocols, reduced to JSON by services.bench.evaluations).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Callable

import torch

from core.device import resolve_device
from services.bench.plan import BenchConfig, BenchConfigError
from services.bench.seed_stages import seed_stages
from services.bench.seed_worker import STOPPED_EXIT
from services.bench.stages import StageRunner, journal_size, stages_ran_since, write_json
from services.bench.stopping import MARKER as TRAIN_MARKER
from services.threads import ThreadPlan, plan_threads

DATA_MARKER = "manifest.json"
# How long an interrupted run waits for its seed workers to save and exit before killing them: a
# small-preset flow step takes up to ~15 s on one time-sliced thread; a worker mid-evaluation stops at once.
WORKER_STOP_GRACE_S = 120.0
# A worker's exit statuses that mean "stopped by a signal, nothing failed": its own 130, or death by SIGINT /
# SIGTERM (before its handlers are in place; and once, in a test, -2 after the worker had caught the
# KeyboardInterrupt and printed its stop line: CPython ends a process by SIGINT when it counted a
# KeyboardInterrupt as unhandled, which we did not trace further).
STOPPED_EXITS = (STOPPED_EXIT, -signal.SIGINT, -signal.SIGTERM)


def run_paper_bench(config: BenchConfig, out_dir: str | Path, *, parallel_seeds: int = 1,
                    threads: int | None = None, rerun_changed: bool = False, redo: Sequence[str] = (),
                    log: Callable[[str], None] = print) -> dict:
    """Run (or continue) the whole benchmark into `out_dir`; returns the report's metrics dict.

    parallel_seeds: seeds trained at the same time, each in a worker process; more than the usable CPUs
    run one thread each, time-sliced (3 seeds on 2 CPUs then end together, instead of the third training
    alone on one CPU while the other idles); threads: torch threads per process instead of the plan's share
    (may oversubscribe); rerun_changed: `out_dir` may hold a benchmark of another plan, whose stages that
    the change touches are redone (services.bench.replan) and the others kept; redo: stage-name patterns
    whose stages, and every stage downstream of them, are redone (after a code change)."""
    from services.bench.running import BENCH_PID, refuse_if_written, running
    from services.bench.task_options import check_task_options

    out = Path(out_dir)
    check_task_options(config, out / "work")   # before anything is written: a typo must not cost the data stages
    # One run at a time in a work dir: a second one (or the first's workers, still saving their step after their
    # parent was killed) would write the same stages. While it runs, `bench carry save` refuses to copy it.
    refuse_if_written(out / "work", "bench paper")
    with running(out / "work" / BENCH_PID):
        return _run_paper_bench(config, out, parallel_seeds=parallel_seeds, threads=threads,
                                rerun_changed=rerun_changed, redo=redo, log=log)


def _run_paper_bench(config: BenchConfig, out: Path, *, parallel_seeds: int, threads: int | None,
                     rerun_changed: bool, redo: Sequence[str], log: Callable[[str], None]) -> dict:
    from services.bench.report import write_bench_report

    started = time.monotonic()
    stages = StageRunner(out / "work", log)
    _check_same_plan(out / "work" / "plan.json", config, rerun_changed=rerun_changed, log=log)
    if redo:
        from services.bench.replan import forget_matching

        forget_matching(config, out / "work", redo, log)
    device = resolve_device(config.device)
    log(f"[bench] paper benchmark, preset {config.preset}, seeds {list(config.seeds)}, device {device}"
        f"{', bf16 training' if config.precision == 'bf16' else ''}, "
        f"{'quick profile' if config.quick else 'full profile'} -> {out}")

    sequential = _thread_plan(1, threads)
    torch.set_num_threads(sequential.threads)
    log(f"[bench] threads, sequential stages: {sequential.describe()}")
    data = _data_stages(stages, config)
    workers = min(parallel_seeds, len(config.seeds))
    if workers > 1:
        parallel = _thread_plan(workers, threads, cap_processes=False)
        log(f"[bench] threads, seeds in parallel: {parallel.describe(independent=True)}")
        journal_start = journal_size(out / "work")
        _run_seed_workers(out, config, parallel, log)
        ran_by_workers = stages_ran_since(out / "work", journal_start)
    else:
        ran_by_workers = []
    results: dict = {"seeds": {}}
    test_records = _load_records(data["test"])
    val_records = _load_records(data["val"])
    for seed in config.seeds:   # after parallel workers, every stage is done and only read back here
        results["seeds"][str(seed)] = seed_stages(stages, config, seed, data, test_records, val_records, device)

    wall = time.monotonic() - started
    metrics = write_bench_report(out, config=config, results=results, stage_seconds=dict(stages.seconds),
                                 wall_time_s=wall, ran=[*ran_by_workers, *stages.ran], stopping=_stopping(out, config),
                                 stage_code=dict(stages.code))
    log(f"[bench] report: {out / 'report.md'} ({wall:.1f} s this run; "
        f"{sum(v for v in stages.seconds.values() if v == v):.1f} s over all stages)")
    return metrics


def run_one_seed(out_dir: str | Path, seed: int, *, log: Callable[[str], None] = print) -> None:
    """Every stage of one seed, with the plan the parent wrote to OUT/work/plan.json (a seed worker)."""
    from services.bench.running import WORKER_PID, refuse_if_written, running

    out = Path(out_dir)
    config = BenchConfig.from_dict(json.loads((out / "work" / "plan.json").read_text()))
    if seed not in config.seeds:
        raise BenchConfigError(f"seed {seed} is not in the plan's seeds {list(config.seeds)}")
    refuse_if_written(out / "work" / f"seed{seed}", f"seed {seed}'s worker")
    with running(out / "work" / f"seed{seed}" / WORKER_PID):
        stages = StageRunner(out / "work", log)
        data = _record_data_stages(stages, config)
        seed_stages(stages, config, seed, data, _load_records(data["test"]), _load_records(data["val"]),
                     resolve_device(config.device))


def _thread_plan(processes: int, threads: int | None, *, cap_processes: bool = True) -> ThreadPlan:
    plan = plan_threads(processes=processes, cap_processes=cap_processes)
    return plan if threads is None else ThreadPlan(cpus=plan.cpus, processes=plan.processes, threads=threads)


def _run_seed_workers(out: Path, config: BenchConfig, plan: ThreadPlan, log: Callable[[str], None]) -> None:
    """Train the seeds in worker processes, `plan.processes` at a time, `plan.threads` threads each."""
    env = {**os.environ, "OMP_NUM_THREADS": str(plan.threads), "MKL_NUM_THREADS": str(plan.threads)}
    pending = [s for s in config.seeds]
    running: dict[int, tuple[subprocess.Popen, Path]] = {}
    failed: list[str] = []
    try:
        while pending or running:
            while pending and len(running) < plan.processes:
                seed = pending.pop(0)
                log_path = out / "work" / f"seed{seed}" / "worker.log"
                log_path.parent.mkdir(parents=True, exist_ok=True)
                with open(log_path, "a") as f:
                    proc = subprocess.Popen(
                        [sys.executable, "-m", "services.bench.seed_worker", "--out", str(out), "--seed", str(seed),
                         "--threads", str(plan.threads), "--parent-pid", str(os.getpid())], stdout=f, stderr=subprocess.STDOUT, env=env,
                        cwd=str(Path(__file__).resolve().parents[2]))
                running[seed] = (proc, log_path)
                log(f"[bench] seed {seed}: worker pid {proc.pid}, {plan.threads} thread(s), log {log_path}")
            time.sleep(1.0)
            for seed, (proc, log_path) in list(running.items()):
                if proc.poll() is not None:
                    del running[seed]
                    if proc.returncode == 0:
                        log(f"[bench] seed {seed}: worker done")
                    elif proc.returncode in STOPPED_EXITS:
                        failed.append(f"seed {seed} (stopped by a signal: {_last_line(log_path)}; rerun the same "
                                      f"command to resume it)")
                        log(f"[bench] seed {seed}: worker stopped by a signal (a rerun resumes it)")
                    else:
                        failed.append(f"seed {seed} (exit {proc.returncode}; last line: {_last_line(log_path)}; "
                                      f"log {log_path})")
                        log(f"[bench] seed {seed}: worker FAILED, exit {proc.returncode}")
    finally:
        # Interrupted: stop our own workers (a rerun resumes them). SIGTERM first: a training stage then
        # finishes the step under way and saves its checkpoint (services/training/stop_signal.py); a
        # worker still running after the grace period is killed and resumes from its last checkpoint.
        for proc, _ in running.values():
            proc.terminate()
        deadline = time.monotonic() + WORKER_STOP_GRACE_S
        for proc, _ in running.values():
            try:
                proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    if failed:
        raise BenchConfigError("seed worker(s) failed: " + "; ".join(failed))


def _last_line(path: Path) -> str:
    try:
        lines = [l for l in path.read_text(errors="replace").splitlines() if l.strip()]
    except OSError:
        return "?"
    return lines[-1][-300:] if lines else "(empty)"


def _stopping(out: Path, config: BenchConfig) -> dict:
    """{seed: {stage: stopping.json}} of every training stage (how long each trained, and why)."""
    found: dict = {}
    for seed in config.seeds:
        for path in sorted((out / "work" / f"seed{seed}").glob(f"*/{TRAIN_MARKER}")):
            found.setdefault(str(seed), {})[path.parent.name] = json.loads(path.read_text())
    return found


def _check_same_plan(path: Path, config: BenchConfig, *, rerun_changed: bool = False,
                     log: Callable[[str], None] = print) -> None:
    """A rerun into the same directory must use the same plan (else its stages would be mixed), unless
    `rerun_changed`: then the stages the change touches are deleted first (services.bench.replan)."""
    from services.bench.plan import BenchConfigError

    current = {k: v for k, v in config.to_dict().items() if k not in ("seeds", "workers", "device")}
    written = json.loads(path.read_text()) if path.exists() else None
    if written is not None and "rules" not in written:
        raise BenchConfigError(f"{path.parent.parent} holds a benchmark of an older n3dmap (fixed step counts, "
                               "no stopping rules); use a new --out")
    if written is not None:
        earlier = {k: v for k, v in written.items() if k not in ("seeds", "workers", "device")}
        earlier.setdefault("precision", "fp32")  # plans written before the option trained in fp32
        earlier.setdefault("task_options", {})  # plans written before the option ran the tasks' defaults
        earlier.setdefault("label_draws", 1)     # plans written before label draws trained one
        earlier.setdefault("world", {})          # plans written before the field: the preset's world
        changed = sorted(k for k in set(earlier) | set(current) if earlier.get(k) != current.get(k))
        if not changed and _workers_change_stages(written, config, path.parent):
            changed = ["workers"]   # Ray workers share out each detector's labels: smaller per-worker batches
        if changed:
            if not rerun_changed:
                raise BenchConfigError(f"{path.parent.parent} holds a benchmark with another plan "
                                       f"(differs in {changed}); use a new --out, the same options, or "
                                       "--rerun-changed to redo only the stages the change touches")
            from services.bench.replan import forget_changed

            log(f"[bench] plan changed in {changed}")
            forget_changed(BenchConfig.from_dict(written), config, path.parent, log)
    write_json(path, config.to_dict())


def _workers_change_stages(earlier: dict, config: BenchConfig, work: Path) -> bool:
    """Whether the run's Ray worker count changed in a way some stage's digest sees (detectors whose
    labels the workers share out; services.bench.plan.BenchConfig.detector_batch_size)."""
    if earlier.get("workers", 0) == config.workers:
        return False
    from services.bench.replan import changed_stages

    return bool(changed_stages(BenchConfig.from_dict(earlier), config, work))


def _load_records(data_dir: Path) -> list[dict]:
    from core.data.shards import ShardDataset

    dataset = ShardDataset(data_dir)
    return [dataset[i] for i in range(len(dataset))]


# ----------------------------------------------------------------------------- data

def _data_specs(config: BenchConfig) -> dict[str, dict]:
    """{"train" | "test" | "val": the arguments of services.bench.data.generate_split} (also each stage's spec)."""
    # `world` only when set: the data stages' specs, so their digests, stay those of plans before the field.
    world = {"world": dict(config.world)} if config.world else {}
    return {"train": dict(preset=config.preset, episodes=config.train_episodes, seed=config.data_seed, split="train",
                          **world),
            "test": dict(preset=config.preset, episodes=config.test_episodes, seed=config.data_seed + 1, split="val",
                         **world),
            "val": dict(preset=config.preset, episodes=config.val_episodes, seed=config.data_seed + 2, split="val",
                        **world)}


def _data_stages(stages: StageRunner, config: BenchConfig) -> dict:
    from services.bench.data import generate_split

    return {split: stages.run(f"data/{split}", DATA_MARKER, lambda d, a=args: generate_split(d, **a), spec=args)
            for split, args in _data_specs(config).items()}


def _record_data_stages(stages: StageRunner, config: BenchConfig) -> dict:
    """The data stages' directories, their digests recorded without running them (a seed worker: the
    parent made the data)."""
    for split, args in _data_specs(config).items():
        stages.record(f"data/{split}", spec=args)
    return {split: stages.dir(f"data/{split}") for split in _data_specs(config)}
