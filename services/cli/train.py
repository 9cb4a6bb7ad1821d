"""`n3dmap train TASK ...`: train a task on an embedded Ray (default), in-process, or on a cluster.

Every task shares the options of `add_common_train_args` and runs through `run_train`. A task's
parser lives in `services/cli/train_tasks/<task>.py` and exposes `register(task_subparsers)`; a
typical one is

    def register(tasks):
        parser = add_task_parser(tasks, "egomotion", help="...")
        parser.add_argument("--scales", type=int, default=3)        # task-specific options
        parser.set_defaults(func=lambda args: run_train("egomotion", args, {"scales": args.scales}))

`task_options` is passed to `core.tasks.build_task(task, preset, **task_options)` on every worker.
"""

from __future__ import annotations

import argparse
import importlib
import os
from pathlib import Path

from core.errors import DataError
from services.cli.argtypes import non_negative_float, positive_float
from services.cli.paths import check_creatable_dir
from services.training.config import TrainConfigError

# Task parser modules under services/cli/train_tasks/, in `n3dmap train --help` order.
TRAIN_TASKS = ("pretrain", "egomotion", "occupancy", "flow", "detector")

# Options that only steer the submission itself and are not forwarded to the cluster's command.
_SUBMIT_ONLY = {"address", "follow", "working_dir", "submission_id"}
# Path options made absolute before they travel to the cluster.
_PATH_OPTIONS = {"data", "run_dir", "init"}


def add_common_train_args(parser: argparse.ArgumentParser) -> None:
    """The options every `n3dmap train TASK` has (None defaults come from the preset)."""
    io = parser.add_argument_group("data and run")
    io.add_argument("--data", required=True, metavar="DIR", help="dataset directory (manifest.json + shards)")
    io.add_argument("--run-dir", required=True, metavar="DIR",
                    help="where checkpoints, metrics.jsonl and the exported bundle/ go; "
                         "rerunning with the same run dir resumes")
    io.add_argument("--preset", default=None,
                    help="model/grid preset (tiny, small, paper); default: the dataset's preset")
    io.add_argument("--init", default=None, metavar="BUNDLE",
                    help="load this bundle's modules into the task before training (kept in the export)")
    io.add_argument("--freeze-features", action="store_true",
                    help="keep the 3D feature encoder (the bundle's 'mapper') fixed")

    opt = parser.add_argument_group("optimisation")
    opt.add_argument("--steps", type=int, default=None, help="total steps (default: preset)")
    opt.add_argument("--batch-size", type=int, default=None, help="records per worker per step (default: preset)")
    opt.add_argument("--lr", type=positive_float, default=None, help="Adam learning rate (default: preset)")
    opt.add_argument("--seed", type=int, default=0, help="seed for weights and data order")
    opt.add_argument("--ema-decay", type=float, default=0.0, metavar="D",
                     help="keep an exponential moving average of the weights with this decay (e.g. 0.995) and "
                          "export it instead of the last step's weights; 0 (default): off")
    opt.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                     help="checkpoint every N steps and at the end (default: preset)")
    opt.add_argument("--log-every", type=int, default=10, metavar="N",
                     help="print progress and write metrics.jsonl every N steps")

    ray = parser.add_argument_group("workers (Ray Train)")
    ray.add_argument("--workers", type=int, default=2,
                     help="Ray Train workers (DDP); 0 runs a plain loop in this process without Ray")
    ray.add_argument("--cpus-per-worker", type=int, default=1,
                     help="CPUs Ray reserves per worker (on a cluster also its torch threads; on the embedded Ray "
                          "the usable CPUs are shared out so that workers × threads never exceeds them)")
    ray.add_argument("--gpus-per-worker", type=non_negative_float, default=0.0,
                     help="GPUs Ray reserves per worker, fractions allowed (default 0: none; with --device cuda)")
    ray.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    ray.add_argument("--precision", choices=("fp32", "bf16"), default="fp32",
                     help="bf16: each forward under bfloat16 autocast on the run's device (CPU or CUDA); "
                          "weights, optimizer and geometry stay float32. Default fp32: on CPU a bf16 step "
                          "measured 0.87-0.99x the fp32 time at the small preset (within noise), so it "
                          "buys little there, and on an H200 whole pretraining steps were slower in bf16 "
                          "(README: Training)")
    ray.add_argument("--max-failures", type=int, default=2,
                     help="restart the workers from the last checkpoint this many times (-1: always)")
    ray.add_argument("--object-store-mb", type=int, default=512,
                     help="object store of the embedded local Ray")

    remote = parser.add_argument_group("cluster (Ray Jobs)")
    remote.add_argument("--address", default=None,
                        help="submit to this Ray cluster's job server (http://HEAD:8265) instead of "
                             "running here; prints the job id")
    remote.add_argument("--follow", action="store_true", help="with --address: stream the job's logs until it ends")
    remote.add_argument("--working-dir", default="auto",
                        help="with --address: directory uploaded as the job's code ('auto': this source "
                             "checkout if any; 'none': rely on n3dmap installed on the cluster)")
    remote.add_argument("--submission-id", default=None, help="with --address: choose the job id")
    # Set on the command a submitted job runs: join the surrounding cluster instead of a local Ray.
    remote.add_argument("--attach", action="store_true", help=argparse.SUPPRESS)


def add_task_parser(task_subparsers, name: str, *, help: str, description: str | None = None
                    ) -> argparse.ArgumentParser:
    """Add `n3dmap train NAME` with the common options; the caller adds its own and sets func."""
    parser = task_subparsers.add_parser(name, help=help, description=description or help)
    add_common_train_args(parser)
    parser.set_defaults(train_parser=parser)
    return parser


def config_from_args(task_name: str, args: argparse.Namespace, task_options: dict):
    """The TrainJobConfig the flags describe (preset defaults resolved later)."""
    from services.training.config import TrainJobConfig

    preset = args.preset or _dataset_preset(args.data) or "tiny"
    return TrainJobConfig(
        task=task_name, data_dir=args.data, run_dir=args.run_dir, preset=preset,
        task_options=task_options, workers=args.workers, cpus_per_worker=args.cpus_per_worker,
        gpus_per_worker=args.gpus_per_worker, device=args.device, precision=args.precision, steps=args.steps,
        batch_size=args.batch_size, lr=args.lr, checkpoint_every=args.checkpoint_every,
        log_every=args.log_every, max_failures=args.max_failures, seed=args.seed, ema_decay=args.ema_decay,
        init_bundle=args.init, freeze=("mapper",) if args.freeze_features else (),
        object_store_mb=args.object_store_mb, attach=args.attach,
    )


def _dataset_preset(data_dir: str) -> str | None:
    """The preset named in the dataset's manifest (None when unreadable: the run reports why)."""
    import json

    try:
        return json.loads((Path(data_dir) / "manifest.json").read_text()).get("preset")
    except (OSError, ValueError, AttributeError):
        return None


def run_train(task_name: str, args: argparse.Namespace, task_options: dict) -> int:
    """Run `n3dmap train TASK` as the flags say: submit (--address) or train here and export."""
    if args.address:
        return _submit(task_name, args)
    from services.training.job import run_training

    if not Path(args.data).is_dir():
        raise DataError(f"--data {args.data}: no such dataset directory")
    check_creatable_dir(args.run_dir, "--run-dir")
    config = config_from_args(task_name, args, task_options)
    if config.workers == 0 and not config.attach:
        # One process trains: it gets every usable CPU (Ray workers get theirs in services.training.job).
        import torch

        from services.threads import plan_threads

        plan = plan_threads(processes=1)
        torch.set_num_threads(plan.threads)
        print(f"threads: {plan.describe()}", flush=True)
    summary = run_training(config)
    outcome = summary.outcome
    if outcome.start_step >= outcome.step:
        print(f"{task_name}: run already at step {outcome.step}; re-exported the bundle")
    loss = outcome.last_metrics.get("loss")
    loss_text = f" (loss {loss:.4g})" if isinstance(loss, (int, float)) else ""
    print(f"{task_name}: finished step {outcome.step} in {summary.seconds:.1f} s{loss_text}; "
          f"bundle: {summary.bundle_dir}")
    return 0


def forwarded_argv(task_name: str, args: argparse.Namespace) -> list[str]:
    """`train TASK ...` reconstructed from the parsed flags (submission-only ones dropped, --attach
    added, paths absolute) — the command a submitted job runs."""
    parser: argparse.ArgumentParser = args.train_parser
    argv = ["train", task_name]
    for action in parser._actions:  # argparse keeps no public list of a parser's options
        if not action.option_strings or action.dest in _SUBMIT_ONLY | {"help", "attach"}:
            continue
        value = getattr(args, action.dest, None)
        if value is None or value == action.default:
            continue
        flag = action.option_strings[-1] if action.option_strings[-1].startswith("--") else action.option_strings[0]
        if isinstance(action, argparse.BooleanOptionalAction):   # --x / --no-x: the one the value says, bare
            argv.append(next(o for o in action.option_strings if o.startswith("--no-") != bool(value)))
        elif isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
            # the flag only when set: a handler may have written the other value (detector's freeze_features)
            if value == action.const:
                argv.append(flag)
        elif isinstance(value, (list, tuple)):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, os.path.abspath(value) if action.dest in _PATH_OPTIONS else str(value)]
    return argv + ["--attach"]


def _submit(task_name: str, args: argparse.Namespace) -> int:
    from services.training import remote

    working_dir = _resolve_working_dir(args.working_dir)
    argv = forwarded_argv(task_name, args)
    job_id = remote.submit(args.address, argv, working_dir=working_dir, submission_id=args.submission_id)
    print(job_id, flush=True)
    if not args.follow:
        print(f"submitted {task_name} as Ray job {job_id}; watch it with "
              f"`n3dmap jobs logs {job_id} --follow --address {args.address}`", flush=True)
        return 0
    status = remote.follow_logs(args.address, job_id)
    print(f"job {job_id}: {status}", flush=True)
    return 0 if status == "SUCCEEDED" else 1


def _resolve_working_dir(choice: str) -> Path | None:
    from services.training.job import PROJECT_ROOT

    if choice == "none":
        return None
    if choice == "auto":
        return PROJECT_ROOT if (PROJECT_ROOT / "pyproject.toml").is_file() else None
    path = Path(choice)
    if not path.is_dir():
        raise TrainConfigError(f"--working-dir {choice}: not a directory")
    return path.resolve()


def register(subparsers) -> None:
    train = subparsers.add_parser(
        "train", help="train a task (pretrain, egomotion, ...) on Ray Train",
        description="Train a task on an embedded local Ray (default), in this process (--workers 0), "
                    "or on a Ray cluster (--address). Rerunning a command resumes its run dir.")
    tasks = train.add_subparsers(dest="task", metavar="TASK", required=True)
    for name in TRAIN_TASKS:
        importlib.import_module(f"services.cli.train_tasks.{name}").register(tasks)
