"""The flow task's default grid step: a ±3/±1/±3 window with ±1 cost boxes (core/tasks/flow.py says why,
measured), for input volumes and features alike, and the CLI's `train flow` passes nothing that overrides it."""

from __future__ import annotations

from core.presets import get_preset
from core.tasks.flow import FlowTask


def test_a_default_flow_task_builds_the_wide_aggregated_grid_step():
    for inputs in ("volume", "features"):
        flow = FlowTask.from_preset(get_preset("tiny"), inputs=inputs).flow
        assert flow.refine_radius == (3, 1, 3) and tuple(flow.refine_aggregate) == (1, 1, 1), inputs
        assert flow.radius == (1, 1, 1)          # the decoders keep the narrow window (their gain: none measured)
        assert flow.config()["refine_radius"] == [3, 1, 3]   # recorded in the bundle, so inference uses it


def test_the_narrow_step_stays_available():
    flow = FlowTask.from_preset(get_preset("tiny"), refine_radius=(1, 1, 1), refine_aggregate=(0, 0, 0)).flow
    assert flow.refine_radius == (1, 1, 1) and tuple(flow.refine_aggregate) == (0, 0, 0)
