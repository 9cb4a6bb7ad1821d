"""Helpers shared by the evaluation kinds: one record -> a batch of one on a device."""

from __future__ import annotations

import numpy as np
import torch

from core.data.batch import records_to_batch

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


def heightmap(occupancy: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Z×Y×X occupancy -> Z×X height in voxels above the grid bottom of the top occupied voxel (NaN if
    none). Y points down, so height = Y − y_index of the smallest occupied y (the paper's heightmaps)."""
    occupied = occupancy >= threshold  # Z×Y×X
    Y = occupancy.shape[1]
    top = np.argmax(occupied, axis=1)  # Z×X
    return np.where(occupied.any(axis=1), (Y - top).astype(np.float32), np.nan)
