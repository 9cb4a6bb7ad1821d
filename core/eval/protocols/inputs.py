"""Pipeline inputs from one record: the record as a batch of one, and one pair of its time steps."""

from __future__ import annotations

import torch

from core.data.batch import records_to_batch
from core.geometry import se3

_KEYS = ("rgb", "depth", "pix_T_cam", "world_T_cam", "world_T_ref")


def record_batch(record: dict, device) -> dict[str, torch.Tensor]:
    """The image/pose keys of one record as a batch of one (see core.data.batch)."""
    return records_to_batch([{k: record[k] for k in _KEYS}], device)


def pair_inputs(batch: dict[str, torch.Tensor], t0: int, t1: int) -> dict[str, torch.Tensor]:
    """Keyword inputs of core.pipeline.estimate_egomotion / estimate_flow for steps t0 -> t1."""
    return {"rgb0": batch["rgb"][:, t0], "depth0": batch["depth"][:, t0], "pix_T_cam0": batch["pix_T_cam"],
            "world_T_cam0": batch["world_T_cam"][:, t0], "rgb1": batch["rgb"][:, t1],
            "depth1": batch["depth"][:, t1], "pix_T_cam1": batch["pix_T_cam"],
            "world_T_cam1": batch["world_T_cam"][:, t1], "world_T_ref0": batch["world_T_ref"][:, t0],
            "world_T_ref1": batch["world_T_ref"][:, t1]}


def with_stabilising_pose(inputs: dict[str, torch.Tensor], ref0_T_ref1: torch.Tensor) -> dict[str, torch.Tensor]:
    """`pair_inputs` whose record poses stabilise frame 1 with `ref0_T_ref1` (B×4×4) instead of the true
    pose: frame 1's whole rig moves in the world (world_T_cam1 and world_T_ref1 by the same D), so its own
    view geometry (cam1_T_ref1) is unchanged and only the relative pose differs. Why not world_T_ref1
    alone: the stabilisation lifts frame 1 with cam1_T_ref1 · ref1_T_ref0 = cam1_T_world · world_T_ref0,
    in which world_T_ref1 cancels (a pose error put there measures nothing)."""
    world_T_ref1 = inputs["world_T_ref1"]
    D = inputs["world_T_ref0"] @ ref0_T_ref1 @ se3.invert(world_T_ref1)  # B×4×4, in the world
    return {**inputs, "world_T_ref1": D @ world_T_ref1, "world_T_cam1": D[:, None] @ inputs["world_T_cam1"]}
