"""Helpers shared by the evaluation reports (their inputs are core.eval.protocols.inputs)."""

from __future__ import annotations

import numpy as np


def heightmap(occupancy: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """Z×Y×X occupancy -> Z×X height in voxels above the grid bottom of the top occupied voxel (NaN if
    none). Y points down, so height = Y − y_index of the smallest occupied y (the paper's heightmaps)."""
    occupied = occupancy >= threshold  # Z×Y×X
    Y = occupancy.shape[1]
    top = np.argmax(occupied, axis=1)  # Z×X
    return np.where(occupied.any(axis=1), (Y - top).astype(np.float32), np.nan)
