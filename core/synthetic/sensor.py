"""Depth sensor effects: LiDAR-like sparsity (a subset of image rows, with dropouts) and Gaussian noise.

Depth is metres along camera Z, 0 = no return. Random draws are made on the CPU from a seeded
generator and then moved to the depth's device, so a seed gives the same pattern on CPU and CUDA.
"""

from __future__ import annotations

import torch


def sparsify_rows(depth: torch.Tensor, *, row_step: int, dropout: float, generator: torch.Generator) -> torch.Tensor:
    """Keep every `row_step`-th image row (scan lines of a LiDAR), drop a `dropout` fraction of those
    returns at random, zero the rest. depth: ...×H×W -> ...×H×W."""
    H = depth.shape[-2]
    rows = torch.zeros(H, dtype=torch.bool)
    rows[(row_step // 2)::row_step] = True  # beams centred in their band
    keep = rows.view(H, 1).expand(depth.shape[-2:])
    if dropout > 0:
        keep = keep & (torch.rand(depth.shape, generator=generator) >= dropout)
    return torch.where(keep.to(depth.device), depth, torch.zeros_like(depth))


def add_depth_noise(depth: torch.Tensor, *, std: float, generator: torch.Generator) -> torch.Tensor:
    """Add N(0, std²) metres to every return (missing stays 0; noisy returns stay positive).
    depth: any shape -> same shape."""
    if std <= 0:
        return depth
    noise = torch.randn(depth.shape, generator=generator, dtype=torch.float32).to(depth.device, depth.dtype)
    noisy = (depth + std * noise).clamp_min(1e-3)
    return torch.where(depth > 0, noisy, depth)
