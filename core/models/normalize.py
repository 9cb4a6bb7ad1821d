"""L2 normalisation over the channel axis, fast on CPU.

`F.normalize(x, dim=1)` on a B×C×… tensor reduces along a strided axis through `linalg.vector_norm`,
which on CPU took 1.0–1.25 ms for a 1×{4,8,16}×32×8×32 volume against 0.03–0.08 ms for the
sum-of-squares form below (1 thread, measured while profiling the tiny stream step, where it was
~9 ms of the step). Same values: x / max(‖x‖, eps), computed as x · rsqrt(max(Σx², eps²)).
"""

from __future__ import annotations

import torch


def l2_normalize_channels(x: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """x: B×C×… -> x / max(‖x‖₂ over C, eps), same shape (as F.normalize(x, dim=1, eps=eps))."""
    return x * x.square().sum(dim=1, keepdim=True).clamp_min(eps * eps).rsqrt()  # B×C×…
