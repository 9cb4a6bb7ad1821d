"""View-regression baseline: L1 between the RGB rendered from the map and the target image."""

from __future__ import annotations

import torch

from core.errors import ShapeError


def rgb_l1(predicted: torch.Tensor, target: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
    """predicted, target: B×3×H×W (same value range); valid: B×1×H×W or None (all pixels).

    Returns the mean absolute error over valid pixels and channels.
    """
    if predicted.shape != target.shape:
        raise ShapeError(f"rgb_l1: predicted {tuple(predicted.shape)} vs target {tuple(target.shape)}")
    err = (predicted.float() - target.float()).abs()  # B×3×H×W
    if valid is None:
        return err.mean()
    w = valid.to(err.dtype).expand_as(err)
    return (err * w).sum() / w.sum().clamp(min=1.0)
