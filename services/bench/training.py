"""One training stage of the benchmark: the same job `n3dmap train TASK` runs, called in-process.

`train_stage` builds the `TrainJobConfig` the CLI would build from its flags and hands it to
`services.training.job.run_training` (workers=0: a plain loop in this process, the default for a
one-machine benchmark; workers=N: an embedded Ray Train job with N workers). The run dir keeps its
checkpoints, so a cut-off stage resumes where it stopped; the exported bundle lands in RUN_DIR/bundle.
"""

from __future__ import annotations

from pathlib import Path

from services.bench.plan import BenchConfig


def train_stage(config: BenchConfig, *, task: str, data_dir: Path, run_dir: Path, steps: int, seed: int,
                task_options: dict | None = None, init_bundle: Path | None = None,
                freeze: tuple[str, ...] = (), batch_size: int | None = None) -> Path:
    """Train `task` to `steps` steps in `run_dir` (resuming) and export; returns the bundle dir."""
    from services.training.config import TrainJobConfig
    from services.training.job import run_training

    job = TrainJobConfig(
        task=task, data_dir=str(data_dir), run_dir=str(run_dir), preset=config.preset,
        task_options=dict(task_options or {}), workers=config.workers, device=config.device,
        steps=steps, batch_size=batch_size or config.batch_size,
        checkpoint_every=max(1, steps // 2), log_every=max(1, steps // 4), max_failures=0 if config.workers == 0 else 1,
        seed=seed, init_bundle=str(init_bundle) if init_bundle else None, freeze=freeze,
    )
    return Path(run_training(job).bundle_dir)
