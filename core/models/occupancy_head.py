"""Occupancy head: one 1×1×1 convolution over the feature map, sigmoid for probabilities (paper appendix)."""

from __future__ import annotations

import torch
from torch import nn

from core.errors import check_shape


class OccupancyHead(nn.Module):
    """B×F×Z×Y×X features -> B×1×Z×Y×X occupancy logits (`probabilities` applies the sigmoid)."""

    def __init__(self, *, in_channels: int = 32) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.conv = nn.Conv3d(in_channels, 1, 1)

    def config(self) -> dict:
        return {"in_channels": self.in_channels}

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """features: B×F×Z×Y×X -> logits B×1×Z×Y×X."""
        check_shape("features", features, (None, self.in_channels, None, None, None))
        return self.conv(features)

    def probabilities(self, features: torch.Tensor) -> torch.Tensor:
        """features: B×F×Z×Y×X -> P(occupied) B×1×Z×Y×X in [0, 1]."""
        return torch.sigmoid(self.forward(features))
