"""Dense L2 between whole aligned tensors at valid positions (paper appendix: coefficient 0.001).

It penalises the distance at every positive correspondence, not only the sampled ones.
"""

from __future__ import annotations

import torch

from core.errors import ShapeError


def dense_l2(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """a, b: B×C×(spatial…); valid: B×1×(spatial…) in [0, 1].

    Returns the valid-weighted mean over positions of the squared distance sum_c (a − b)².
    """
    if a.shape != b.shape:
        raise ShapeError(f"dense_l2: shapes {tuple(a.shape)} and {tuple(b.shape)} differ")
    sq = ((a.float() - b.float()) ** 2).sum(dim=1, keepdim=True)  # B×1×(spatial…)
    w = valid.to(sq.dtype)
    return (sq * w).sum() / w.sum().clamp(min=1.0)
