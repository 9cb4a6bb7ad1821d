"""Stack records (docs/data.md#records) into one batch of tensors for the task steps.

Output keys and shapes (B records):
    rgb          float32 B×T×V×3×H×W in [0, 1]   (from uint8 T×V×H×W×3)
    depth        float32 B×T×V×H×W metres, 0 = missing
    pix_T_cam    float32 B×V×4×4
    world_T_cam  float32 B×T×V×4×4
    world_T_ref  float32 B×T×4×4
    boxes        float32 B×T×K×7 (world frame, as stored)
    box_valid    bool    B×T×K
    box_id       int32   B×K
    box_moving   bool    B×K
Keys a record lacks are left out (box keys are optional for pretraining); all records must agree
in every shape.
"""

from __future__ import annotations

import numpy as np
import torch

from core.errors import DataError

_REQUIRED = ("rgb", "depth", "pix_T_cam", "world_T_cam", "world_T_ref")
_FLOAT_KEYS = ("depth", "pix_T_cam", "world_T_cam", "world_T_ref", "boxes")
_OPTIONAL = ("boxes", "box_valid", "box_id", "box_moving")


def records_to_batch(records: list[dict], device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """list of B records (dict of numpy arrays) -> dict of batched tensors on `device` (see module doc)."""
    if not records:
        raise DataError("records_to_batch: empty list of records")
    batch: dict[str, torch.Tensor] = {}
    for key in _REQUIRED + _OPTIONAL:
        present = [key in r for r in records]
        if not any(present):
            if key in _REQUIRED:
                raise DataError(f"records_to_batch: records lack required key {key!r}")
            continue
        if not all(present):
            raise DataError(f"records_to_batch: key {key!r} present in some records but not all")
        arrays = [np.asarray(r[key]) for r in records]
        shapes = {a.shape for a in arrays}
        if len(shapes) != 1:
            raise DataError(f"records_to_batch: key {key!r} has differing shapes {sorted(shapes)}")
        stacked = torch.from_numpy(np.stack(arrays))
        if key == "rgb":
            if stacked.dtype != torch.uint8 or stacked.ndim != 6 or stacked.shape[-1] != 3:
                raise DataError(f"records_to_batch: rgb must be uint8 T×V×H×W×3, got {arrays[0].dtype} "
                                f"{arrays[0].shape}")
            # contiguous: a permuted (channels-last) image trips a torch 2.13 CPU conv-backward segfault
            stacked = stacked.to(device).permute(0, 1, 2, 5, 3, 4).contiguous().float() / 255.0  # B×T×V×3×H×W
        elif key in _FLOAT_KEYS:
            stacked = stacked.to(device=device, dtype=torch.float32)
        else:
            stacked = stacked.to(device)
        batch[key] = stacked
    return batch
