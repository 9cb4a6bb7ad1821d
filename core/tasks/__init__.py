"""Training steps: `build_task(name, preset, **options)` -> an nn.Module task.

A task's `forward(batch) -> dict[str, Tensor]` returns `loss` (scalar to minimise) plus named scalar
metrics; `exported_modules() -> dict[str, nn.Module]` names what a bundle keeps. `batch` comes from
`core.data.batch.records_to_batch`. The table maps each task name to "module:factory"; a factory is
called as factory(preset, **options). Parts that add a task add one line here.
"""

from __future__ import annotations

import importlib

from torch import nn

from core.presets import Preset, get_preset

TASKS: dict[str, str] = {
    "pretrain": "core.tasks.pretrain:PretrainTask.from_preset",
    "egomotion": "core.tasks.egomotion:EgomotionTask.from_preset",
    "occupancy": "core.tasks.occupancy:OccupancyTask.from_preset",
    "flow": "core.tasks.flow:FlowTask.from_preset",
    "detector": "core.tasks.detector:DetectorTask.from_preset",
}


def build_task(name: str, preset: Preset | str, **options) -> nn.Module:
    """Build task `name` at `preset` (a Preset or its name); `options` go to the task's factory
    (pretrain: objective="contrastive"|"regression", render_scale, seed, coefficients…)."""
    if isinstance(preset, str):
        preset = get_preset(preset)
    try:
        path = TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)}") from None
    module_name, attr = path.split(":")
    factory = importlib.import_module(module_name)
    for part in attr.split("."):
        factory = getattr(factory, part)
    return factory(preset, **options)
