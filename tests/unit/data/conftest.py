"""Fixtures of the data tests: small valid records built by hand (no synthetic generator needed)."""

from __future__ import annotations

import numpy as np
import pytest


def build_record(*, T: int = 2, V: int = 2, H: int = 4, W: int = 6, K: int = 3, seed: int = 0) -> dict:
    """A valid record of the record schema (docs/data.md#records) with random contents (deterministic by seed)."""
    rng = np.random.default_rng(seed)
    pix_T_cam = np.tile(np.eye(4, dtype=np.float32), (V, 1, 1))  # V×4×4
    pix_T_cam[:, 0, 0] = pix_T_cam[:, 1, 1] = 5.0
    pix_T_cam[:, 0, 2], pix_T_cam[:, 1, 2] = (W - 1) / 2, (H - 1) / 2
    world_T_cam = np.tile(np.eye(4, dtype=np.float32), (T, V, 1, 1))  # T×V×4×4
    world_T_cam[..., :3, 3] = rng.normal(size=(T, V, 3))
    world_T_ref = np.tile(np.eye(4, dtype=np.float32), (T, 1, 1))  # T×4×4
    world_T_ref[:, :3, 3] = rng.normal(size=(T, 3))
    return {
        "rgb": rng.integers(0, 256, size=(T, V, H, W, 3), dtype=np.uint8),
        "depth": rng.uniform(0, 10, size=(T, V, H, W)).astype(np.float32),
        "pix_T_cam": pix_T_cam,
        "world_T_cam": world_T_cam,
        "world_T_ref": world_T_ref,
        "boxes": rng.normal(size=(T, K, 7)).astype(np.float32),
        "box_valid": rng.uniform(size=(T, K)) > 0.3,
        "box_id": np.arange(K, dtype=np.int32) + 10,
        "box_moving": rng.uniform(size=K) > 0.5,
    }


@pytest.fixture
def make_record():
    return build_record
