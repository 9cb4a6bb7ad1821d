"""One training stage of the benchmark: the job `n3dmap train TASK` runs, called in-process, for as
long as the stage's stopping rule says (services.bench.stopping).

`train_stage` builds the `TrainJobConfig` the CLI would build from its flags and hands it to
`services.training.job.run_training` (workers=0: a plain loop in this process, the default for a
one-machine benchmark; workers=N: an embedded Ray Train job with N workers), in chunks when the rule
asks for held-out evaluations. The run dir keeps its checkpoints, so a cut-off stage resumes where it
stopped; the chosen bundle lands in RUN_DIR/selected and RUN_DIR/stopping.json says how it was chosen.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from services.bench.plan import BenchConfig
from services.bench.stopping import SELECTED, StageRule, heldout_task_loss, train_by_rule


_ONE_CALL_CHECKPOINT_EVERY = 200


def train_stage(config: BenchConfig, *, task: str, data_dir: Path, run_dir: Path, rule: StageRule, seed: int,
                heldout_records: list[dict], task_options: dict | None = None, init_bundle: Path | None = None,
                freeze: tuple[str, ...] = (), batch_size: int | None = None,
                log: Callable[[str], None] = print) -> Path:
    """Train `task` by `rule` in `run_dir` (resuming); returns the chosen bundle dir (RUN_DIR/selected)."""
    from core.data.shards import load_manifest
    from services.training.config import TrainJobConfig
    from services.training.job import latest_checkpoint_dir, run_training

    def job(steps: int) -> TrainJobConfig:
        # a stage trained in one call (fixed, epochs) checkpoints at least every 200 steps: a cut-off run
        # resumes there instead of from the stage's start or middle
        every = rule.eval_every if rule.kind == "plateau" else max(1, min(steps // 2, _ONE_CALL_CHECKPOINT_EVERY))
        return TrainJobConfig(
            task=task, data_dir=str(data_dir), run_dir=str(run_dir), preset=config.preset,
            task_options=dict(task_options or {}), workers=config.workers, device=config.device,
            precision=config.precision,
            steps=steps, batch_size=batch_size or config.batch_size, checkpoint_every=every,
            log_every=max(1, min(every, steps) // 2), max_failures=0 if config.workers == 0 else 1,
            seed=seed, init_bundle=str(init_bundle) if init_bundle else None, freeze=freeze,
            ema_decay=rule.ema_decay,
        ).resolved()

    def train_to(steps: int) -> Path:
        return Path(run_training(job(steps)).bundle_dir)

    def heldout(step: int) -> float:
        j = job(step)
        return heldout_task_loss(j, heldout_records, checkpoint_dir=latest_checkpoint_dir(j), batch_size=j.batch_size)

    records = int(load_manifest(data_dir)["num_records"])
    # an "epochs" rule counts the records a step consumes: every worker's batch
    train_by_rule(rule, Path(run_dir), train_to=train_to, heldout_loss=heldout, records=records,
                  batch_size=job(rule.max_steps).batch_size * max(1, config.workers), log=log)
    return Path(run_dir) / SELECTED
