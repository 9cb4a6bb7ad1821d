"""TrainJobConfig: everything one training run needs, as one typed, JSON-serialisable value.

The CLI builds it from flags (`services/cli/train.py`), the driver hands it to every Ray Train
worker as the loop config, and every checkpoint stores it so a rerun can check it resumes the same
run. Preset-dependent defaults (steps, batch size, lr, checkpoint cadence) are resolved once, in
`resolve_defaults`, so the stored config says exactly what ran.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

from core.errors import N3dmapError

DEVICES = ("auto", "cpu", "cuda")
PRECISIONS = ("fp32", "bf16")


class TrainConfigError(N3dmapError):
    """A training option is out of range or inconsistent with the others."""


@dataclass(frozen=True)
class TrainJobConfig:
    """One training run.

    `task` names a `core.tasks.build_task` task and `task_options` its keyword options (for
    `pretrain`: `{"objective": "contrastive"}`). Fields left `None` take the preset's
    `TrainDefaults` in `resolve_defaults`.
    """

    task: str
    data_dir: str
    run_dir: str
    preset: str = "tiny"
    task_options: dict = field(default_factory=dict)
    workers: int = 0                      # 0: plain in-process loop, no Ray
    cpus_per_worker: int = 1
    gpus_per_worker: float = 0.0
    device: str = "auto"                  # auto: cuda when the worker has a GPU, else cpu
    steps: int | None = None
    batch_size: int | None = None         # per worker
    lr: float | None = None
    checkpoint_every: int | None = None
    keep_checkpoints: int = 2
    log_every: int = 10
    max_failures: int = 0
    seed: int = 0
    init_bundle: str | None = None        # warm start: load this bundle's modules before step 1
    freeze: tuple[str, ...] = ()          # exported module names kept fixed (e.g. ("mapper",))
    grad_clip: float = 10.0               # max global grad norm; 0 disables clipping
    # > 0: keep an exponential moving average of the weights with this decay (weight_average.py) and
    # export it, and score it in the benchmark's held-out stopping rule, instead of the last step's weights
    ema_decay: float = 0.0
    # "bf16": the task's forward (loss included) under torch.autocast(device type, bfloat16), on CPU and
    # CUDA alike: convolutions and matmuls run in bf16, the ops autocast lists as float32 stay float32,
    # and the weights, gradients, Adam state and geometry (core/precision.py) stay float32. "fp32": no
    # autocast, the default (on CPU a bf16 step measured 0.87-0.99x fp32's at small: README "Training").
    precision: str = "fp32"
    object_store_mb: int = 512            # embedded Ray's object store (Ray Data streams through it)
    attach: bool = False                  # join the Ray cluster this process runs in (Ray Jobs)
    # Fault injection for tests: on the first attempt only, the rank-0 worker process exits hard
    # (os._exit) when it reaches this step. A marker file in the run dir makes it one-shot.
    fault_at_step: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "task_options", dict(self.task_options))
        object.__setattr__(self, "freeze", tuple(self.freeze))
        if self.workers < 0:
            raise TrainConfigError(f"--workers must be >= 0, got {self.workers}")
        if self.cpus_per_worker < 1:
            raise TrainConfigError(f"cpus per worker must be >= 1, got {self.cpus_per_worker}")
        if not (math.isfinite(self.gpus_per_worker) and self.gpus_per_worker >= 0):
            raise TrainConfigError(f"--gpus-per-worker must be >= 0, got {self.gpus_per_worker}")
        if self.gpus_per_worker > 0 and self.workers == 0:
            raise TrainConfigError("--gpus-per-worker needs --workers >= 1 (Ray schedules the GPUs)")
        if self.device not in DEVICES:
            raise TrainConfigError(f"--device must be one of {DEVICES}, got {self.device!r}")
        if self.precision not in PRECISIONS:
            raise TrainConfigError(f"--precision must be one of {PRECISIONS}, got {self.precision!r}")
        for name in ("steps", "batch_size", "checkpoint_every"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise TrainConfigError(f"--{name.replace('_', '-')} must be >= 1, got {value}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise TrainConfigError(f"--ema-decay must lie in [0, 1) (0: off), got {self.ema_decay}")
        if self.lr is not None and not (math.isfinite(self.lr) and self.lr > 0):
            raise TrainConfigError(f"--lr must be > 0, got {self.lr}")
        if self.object_store_mb < 1:
            raise TrainConfigError(f"--object-store-mb must be >= 1, got {self.object_store_mb}")
        if self.max_failures < -1:
            raise TrainConfigError(f"--max-failures must be >= -1 (-1: retry forever), got {self.max_failures}")
        if self.log_every < 1:
            raise TrainConfigError(f"--log-every must be >= 1, got {self.log_every}")
        if self.keep_checkpoints < 1:
            raise TrainConfigError(f"keep_checkpoints must be >= 1, got {self.keep_checkpoints}")

    # -- derived paths -------------------------------------------------------------------------

    @property
    def run_path(self) -> Path:
        return Path(self.run_dir)

    @property
    def metrics_path(self) -> Path:
        return self.run_path / "metrics.jsonl"

    @property
    def bundle_path(self) -> Path:
        return self.run_path / "bundle"

    @property
    def local_checkpoint_root(self) -> Path:
        """Where the in-process loop (workers=0) keeps its checkpoints."""
        return self.run_path / "checkpoints"

    @property
    def ray_storage_name(self) -> str:
        """RunConfig(name=...) under storage_path=run_dir: Ray Train keeps its checkpoints here."""
        return "ray_train"

    @property
    def fault_marker_path(self) -> Path:
        return self.run_path / ".fault_injected"

    # -- (de)serialisation ---------------------------------------------------------------------

    def to_dict(self) -> dict:
        d = asdict(self)
        d["freeze"] = list(self.freeze)
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @staticmethod
    def from_dict(d: dict) -> "TrainJobConfig":
        known = {f.name for f in fields(TrainJobConfig)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise TrainConfigError(f"unknown training config keys {unknown}")
        return TrainJobConfig(**d)

    def resolved(self) -> "TrainJobConfig":
        """Fill preset defaults and make paths absolute (workers may run in another cwd)."""
        return resolve_defaults(self)

    def identity(self) -> dict:
        """The fields a resumed run must share with the run that wrote the checkpoint."""
        return {"task": self.task, "task_options": self.task_options, "preset": self.preset,
                "ema_decay": self.ema_decay}


# Tasks that build a mapper (their configs take `encoder_full_res`, which must match the mapper they load).
MAPPER_TASKS = ("pretrain", "occupancy", "flow", "detector")


def init_mapper_options(task: str, task_options: dict, init_bundle: str | None) -> dict:
    """`task_options` plus the init bundle's mapper shape where the options leave it out: a task that
    builds a mapper and warm-starts from a bundle gets that mapper's `encoder_full_res` (its
    full-resolution branch), so `--init` of a bundle pretrained with `--encoder-full-res N` needs no
    repeat of the flag. Options that set it explicitly win (a mismatch then fails at load, by name)."""
    if task not in MAPPER_TASKS or not init_bundle or "encoder_full_res" in task_options:
        return task_options
    from core.bundle import read_bundle_meta

    mapper = read_bundle_meta(init_bundle)["modules"].get("mapper")
    full_res = int(((mapper or {}).get("config") or {}).get("full_res", 0))
    return {**task_options, "encoder_full_res": full_res} if full_res else task_options


def resolve_defaults(config: TrainJobConfig) -> TrainJobConfig:
    """Return `config` with `None` fields taken from the preset, absolute paths, and the init bundle's
    mapper shape in the task options (`init_mapper_options`)."""
    from core.presets import get_preset

    try:
        preset = get_preset(config.preset)
    except ValueError as e:
        raise TrainConfigError(str(e)) from None
    defaults = preset.train
    return replace(
        config,
        data_dir=os.path.abspath(config.data_dir),
        run_dir=os.path.abspath(config.run_dir),
        init_bundle=os.path.abspath(config.init_bundle) if config.init_bundle else None,
        task_options=init_mapper_options(config.task, config.task_options, config.init_bundle),
        steps=config.steps if config.steps is not None else defaults.steps,
        batch_size=config.batch_size if config.batch_size is not None else defaults.batch_size,
        # flow trains at the preset's flow_lr (the paper: 1e-4 for flow), every other task at lr
        lr=config.lr if config.lr is not None else (defaults.flow_lr if config.task == "flow" else defaults.lr),
        checkpoint_every=(config.checkpoint_every if config.checkpoint_every is not None
                          else defaults.checkpoint_every),
    )
