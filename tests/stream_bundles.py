"""A stream bundle of freshly initialised modules (shared by the bridge's integration test and its
benchmark).

Untrained, the flow and egomotion modules are correlators already: the flow module's last layer is
a soft-argmax over cosine costs and its learned decoders start at zero, and the egomotion module is a
soft-argmax over candidate rotations × shifts. With the moving-object post-processing (frame 0's
observed voxels above its ground plane) they find real moving cars: on the tiny synthetic stream of
seed 1, 9 of 15 boxes lie within 2 m of a moving car's centre (measured; the integration test checks
it). No occupancy head: the observed voxels gate the boxes.
"""

from __future__ import annotations

from pathlib import Path


def untrained_stream_bundle(preset_name: str, out: Path, *, provenance: dict) -> Path:
    """Mapper, flow and egomotion modules of `preset_name`, freshly initialised (seed 0), saved under `out`."""
    import torch

    from core.bundle import save_bundle
    from core.presets import get_preset
    from core.tasks.egomotion import EgomotionTask
    from core.tasks.flow import FlowTask

    torch.manual_seed(0)
    preset = get_preset(preset_name)
    flow_task = FlowTask.from_preset(preset)
    modules = {"mapper": flow_task.mapper, "flow": flow_task.flow,
               "egomotion": EgomotionTask.from_preset(preset).egomotion}
    save_bundle(out, modules=modules, preset=preset, provenance=provenance, metrics={})
    return out
