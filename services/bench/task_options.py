"""`bench paper --task-options`: every training stage's options checked before the run starts.

The plan checks the option *kinds* ("pretrain", "flow_features", …) and the protocol's own options, but the
fields inside them belong to the tasks' config dataclasses (core/tasks/*.py), and a task refuses an unknown
field or a bad value only when it is built — at its stage, which in a full run may come hours after the data
and the stages before it. Here each distinct (task, options) pair the plan will train is built once, with no
data and no training (a few milliseconds each: building a task builds its modules' weights), and the first
refusal ends the run before anything is written, naming the stage, the options and the task's own message.
"""

from __future__ import annotations

import json
from pathlib import Path

from core.errors import N3dmapError
from services.bench.plan import BenchConfig, BenchConfigError


def check_task_options(config: BenchConfig, work: Path) -> None:
    """BenchConfigError naming the stage and field unless every training stage's task builds with its options."""
    from core.tasks import build_task
    from services.bench.replan import _dry_run

    checked: set[tuple[str, str]] = set()
    for name, spec in _dry_run(config, Path(work)).specs.items():
        if "task" not in spec:   # data stages and evaluations
            continue
        options = dict(spec.get("task_options") or {})
        key = (spec["task"], json.dumps(options, sort_keys=True))
        if key in checked:
            continue
        checked.add(key)
        try:
            build_task(spec["task"], config.preset, **options)
        except (TypeError, ValueError, N3dmapError) as e:
            raise BenchConfigError(f"--task-options: stage {name} (task {spec['task']}) cannot be built with "
                                   f"options {json.dumps(options, sort_keys=True)}: {e}") from None
