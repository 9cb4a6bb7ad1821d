"""A bundle of freshly initialised stream modules that still produces flow and boxes (shared by the
stream bridge's integration test and its benchmark)."""

from __future__ import annotations

from pathlib import Path


def random_stream_bundle(preset_name: str, out: Path, *, provenance: dict) -> Path:
    """Mapper, flow, occupancy and egomotion modules of `preset_name` saved under `out`. The flow's
    zero-initialised last convs get random weights (an untrained flow module predicts exactly zero)
    and the occupancy head a bias that keeps part of the grid."""
    import torch

    from core.bundle import save_bundle
    from core.presets import get_preset
    from core.tasks.egomotion import EgomotionTask
    from core.tasks.flow import FlowTask
    from core.tasks.occupancy import OccupancyTask

    torch.manual_seed(0)
    preset = get_preset(preset_name)
    flow_task = FlowTask.from_preset(preset)
    occupancy = OccupancyTask.from_preset(preset).occupancy
    with torch.no_grad():
        for p in flow_task.flow.parameters():
            if p.dim() > 1 and not p.any():
                p.normal_(std=0.3)
        occupancy.conv.weight.normal_(std=2.0)
        occupancy.conv.bias.fill_(1.0)
    modules = {"mapper": flow_task.mapper, "flow": flow_task.flow, "occupancy": occupancy,
               "egomotion": EgomotionTask.from_preset(preset).egomotion}
    save_bundle(out, modules=modules, preset=preset, provenance=provenance, metrics={})
    return out
