"""How long a benchmark stage trains: a fixed count, a held-out plateau, or epochs over the labels.

`StageRule` says it (plan.py gives one per stage and preset):

Any rule may keep a moving average of the weights (`ema_decay` > 0): the stage's bundles are then the
average's weights, and a plateau rule scores those (a constant learning rate leaves each step's weights
noisy; measured in plan.py).

- "fixed":   exactly `max_steps` steps (the quick profile, and `--<stage>-steps N` on the CLI);
- "plateau": train in chunks of `eval_every` steps; after each chunk, score the task's own loss on
             held-out records (the benchmark's validation split, never the test split) with a fixed
             seed; stop once `patience` evaluations in a row brought no relative drop of at least
             `min_improvement` below the best, or at `max_steps`; never before `min_steps`. The stage's
             bundle is the best evaluation's (early stopping keeps the best weights), where "best"
             moves only on such a drop (Keras's `min_delta`): of losses 1.000, 0.997, 0.994, 0.992
             the first stays the best although the last is 0.8 % lower;
- "epochs":  `epochs` passes over the stage's training records (the detector's labelled records:
             ceil(records / batch) steps each), clamped to [`min_steps`, `max_steps`] — so 2 labelled
             records and 64 get the same number of looks at each label instead of the same step count.

`train_by_rule` runs one stage and writes RUN_DIR/stopping.json (the rule, each evaluation, the steps
actually run, why it stopped) last, atomically: it is the stage's completion marker. A stage cut off
mid-way resumes from its last checkpoint and its recorded evaluations (RUN_DIR/stopping.partial.json).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import torch

from core.device import resolve_device
from core.errors import N3dmapError
from services.bench.stages import write_json
from services.durable import fsync_path, fsync_tree

RULE_KINDS = ("fixed", "plateau", "epochs")
MARKER = "stopping.json"
SELECTED = "selected"          # RUN_DIR/selected/: the stage's chosen bundle
CRITERION_SEED = 12345         # the held-out loss samples (views, negatives, motions) with this seed


class StageRuleError(N3dmapError):
    """A stopping rule is inconsistent."""


@dataclass(frozen=True)
class StageRule:
    """How long one stage trains (module docstring)."""

    kind: str
    max_steps: int
    min_steps: int = 1
    eval_every: int = 0              # plateau
    patience: int = 0                # plateau
    min_improvement: float = 0.0     # plateau: relative drop of the held-out loss that counts
    epochs: int = 0                  # epochs
    # > 0: the stage keeps a moving average of its weights with this decay (services/training/
    # weight_average.py); its bundles, and the held-out loss a plateau rule scores, are the average's
    ema_decay: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in RULE_KINDS:
            raise StageRuleError(f"stopping rule kind must be one of {RULE_KINDS}, got {self.kind!r}")
        if self.max_steps < 1 or not 1 <= self.min_steps <= self.max_steps:
            raise StageRuleError(f"need 1 <= min_steps ({self.min_steps}) <= max_steps ({self.max_steps})")
        if self.kind == "plateau" and (self.eval_every < 1 or self.patience < 1 or self.min_improvement < 0):
            raise StageRuleError("a plateau rule needs eval_every >= 1, patience >= 1 and min_improvement >= 0")
        if self.kind == "epochs" and self.epochs < 1:
            raise StageRuleError("an epochs rule needs epochs >= 1")
        if not 0.0 <= self.ema_decay < 1.0:
            raise StageRuleError(f"ema_decay must lie in [0, 1) (0: no weight average), got {self.ema_decay}")

    @staticmethod
    def fixed(steps: int, *, ema_decay: float = 0.0) -> "StageRule":
        return StageRule(kind="fixed", max_steps=steps, min_steps=steps, ema_decay=ema_decay)

    def describe(self) -> str:
        average = f"; weights: moving average, decay {self.ema_decay:g}" if self.ema_decay else ""
        if self.kind == "fixed":
            return f"fixed {self.max_steps} steps{average}"
        if self.kind == "epochs":
            return (f"{self.epochs} epochs over its records, within [{self.min_steps}, {self.max_steps}] "
                    f"steps{average}")
        return (f"held-out loss every {self.eval_every} steps; stop after {self.patience} evaluations without a "
                f"{self.min_improvement:.0%} drop below the best (the best's weights kept), within "
                f"[{self.min_steps}, {self.max_steps}] steps{average}")

    def epoch_steps(self, records: int, batch_size: int) -> int:
        """Steps of an "epochs" rule for `records` training records at `batch_size` per step."""
        per_epoch = math.ceil(records / batch_size)
        return min(self.max_steps, max(self.min_steps, self.epochs * per_epoch))

    def to_dict(self) -> dict:
        d = asdict(self)
        if not d["ema_decay"]:
            # left out when off, as plans and stage digests written before the field have it: those stages
            # stay unchanged for `bench paper --rerun-changed`
            del d["ema_decay"]
        return d


@dataclass(frozen=True)
class Evaluation:
    step: int
    loss: float


def plateau_decision(rule: StageRule, history: list[Evaluation]) -> tuple[bool, int, str]:
    """(stop?, best step, reason) after the evaluations so far (in step order)."""
    best, best_step, since_best = math.inf, 0, 0
    for e in history:
        # A drop smaller than min_improvement neither moves the best nor resets the patience.
        if math.isfinite(e.loss) and (best == math.inf or e.loss < best * (1.0 - rule.min_improvement)):
            best, best_step, since_best = e.loss, e.step, 0
        else:
            since_best += 1
    last = history[-1].step if history else 0
    if last >= rule.max_steps:
        return True, best_step, f"reached max_steps {rule.max_steps}"
    if last >= rule.min_steps and since_best >= rule.patience:
        return True, best_step, (f"no {rule.min_improvement:.0%} drop of the held-out loss in {since_best} "
                                 f"evaluations since step {best_step}")
    return False, best_step, ""


def train_by_rule(rule: StageRule, run_dir: Path, *, train_to: Callable[[int], Path],
                  heldout_loss: Callable[[int], float] | None, records: int, batch_size: int,
                  log: Callable[[str], None] = print) -> dict:
    """Run one stage by `rule` and write RUN_DIR/stopping.json; returns its content.

    train_to(steps) trains the run (resuming) until `steps` and returns its exported bundle dir;
    heldout_loss(step) scores the run's checkpoint at `step` on held-out records (plateau only).
    """
    run_dir = Path(run_dir)
    partial = run_dir / "stopping.partial.json"
    if rule.kind in ("fixed", "epochs"):
        steps = rule.max_steps if rule.kind == "fixed" else rule.epoch_steps(records, batch_size)
        bundle = train_to(steps)
        _select(bundle, run_dir)
        result = {"rule": rule.to_dict(), "describe": rule.describe(), "steps_run": steps, "selected_step": steps,
                  "reason": "fixed step count" if rule.kind == "fixed" else
                  f"{rule.epochs} epochs × {math.ceil(records / batch_size)} steps ({records} records, batch "
                  f"{batch_size}), clamped to [{rule.min_steps}, {rule.max_steps}]", "evaluations": []}
        write_json(run_dir / MARKER, result)
        return result

    if heldout_loss is None:
        raise StageRuleError("a plateau rule needs a held-out criterion")
    history = [Evaluation(**e) for e in (json.loads(partial.read_text())["evaluations"] if partial.exists() else [])]
    while True:
        stop, best_step, reason = plateau_decision(rule, history)
        if stop:
            break
        step = min(rule.max_steps, (history[-1].step if history else 0) + rule.eval_every)
        bundle = train_to(step)
        loss = float(heldout_loss(step))
        history.append(Evaluation(step=step, loss=loss))
        _, new_best, _ = plateau_decision(rule, history)
        if new_best == step:
            _select(bundle, run_dir)   # keep the best weights so far
        log(f"  held-out loss at step {step}: {loss:.4g}" + (" (best)" if new_best == step else ""))
        write_json(partial, {"evaluations": [asdict(e) for e in history]})
    if not (run_dir / SELECTED / "bundle.json").exists():
        raise StageRuleError(f"{run_dir}: no held-out evaluation was finite; nothing to select")
    result = {"rule": rule.to_dict(), "describe": rule.describe(), "steps_run": history[-1].step,
              "selected_step": best_step, "reason": reason, "evaluations": [asdict(e) for e in history]}
    write_json(run_dir / MARKER, result)
    return result


def heldout_task_loss(job, records: list[dict], *, checkpoint_dir: Path, batch_size: int) -> float:
    """Mean `loss` of the job's task at `checkpoint_dir` over `records` (eval mode, no gradient, a fixed
    seed so that every evaluation draws the same views, negatives and synthetic motions)."""
    from services.training.checkpoints import load_checkpoint
    from services.training.loop import CORE_TASKS

    device = resolve_device(job.device)
    task = CORE_TASKS.build(job, device)
    load_checkpoint(checkpoint_dir, task=task, averaged_weights=True)  # the weights the export would hold
    task.eval()
    rng_state = torch.random.get_rng_state()
    torch.manual_seed(CRITERION_SEED)
    total, count = 0.0, 0
    try:
        with torch.no_grad():
            for start in range(0, len(records) - batch_size + 1, batch_size):
                batch = CORE_TASKS.to_batch(records[start:start + batch_size], device)
                loss = float(task(batch)["loss"])
                total, count = total + loss, count + 1
    finally:
        torch.random.set_rng_state(rng_state)
    if count == 0:
        raise StageRuleError(f"{len(records)} held-out records make no batch of {batch_size}")
    return total / count


def _select(bundle_dir: Path, run_dir: Path) -> None:
    """Copy the bundle to RUN_DIR/selected atomically (a reader never sees half a bundle), flushed to disk before
    the rename that makes it the selection (services.durable: the held-out history and the stage's marker that
    name it are fsynced too, so after a power loss they never point at empty weights)."""
    tmp = run_dir / (SELECTED + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(bundle_dir, tmp)
    fsync_tree(tmp)
    old = run_dir / (SELECTED + ".old")
    if (run_dir / SELECTED).exists():
        shutil.rmtree(old, ignore_errors=True)
        os.replace(run_dir / SELECTED, old)
    os.replace(tmp, run_dir / SELECTED)
    fsync_path(run_dir)
    shutil.rmtree(old, ignore_errors=True)
