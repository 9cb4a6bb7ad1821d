"""Candidate rotations of the egomotion module: a small Cartesian set of Euler offsets around identity.

Conventions (docs/conventions.md#poses, core.geometry.se3): rotations are about the `ref` frame's own axes through
its origin (the ego camera centre, which is the grid centre in every preset); R = Rz·Ry·Rx. Y points
down, so a rotation about Y is yaw — the dominant rotation of ground vehicles; presets give yaw the
largest step ("yaw-heavy").
"""

from __future__ import annotations

import itertools
import math

import torch

from core.geometry import se3


def candidate_angles(steps_deg: tuple[float, float, float], counts: tuple[int, int, int] = (3, 3, 3), *,
                     dtype=torch.float32, device=None) -> torch.Tensor:
    """The Euler offsets (rx, ry, rz) radians of `candidate_rotations`, in its order: R×3."""
    if any(n < 1 or n % 2 == 0 for n in counts):
        raise ValueError(f"candidate_rotations: counts must be odd and positive, got {counts}")
    axes = [[(k - (n - 1) / 2) * math.radians(s) for k in range(n)] for s, n in zip(steps_deg, counts)]
    return torch.tensor(list(itertools.product(*axes)), dtype=torch.float64).to(dtype=dtype, device=device)  # R×3


def candidate_rotations(steps_deg: tuple[float, float, float], counts: tuple[int, int, int] = (3, 3, 3), *,
                        dtype=torch.float32, device=None) -> torch.Tensor:
    """Cartesian product of per-axis offsets k·step for k in [-(n-1)/2, (n-1)/2].

    steps_deg: (rx, ry, rz) spacing in degrees; counts: offsets per axis (odd, so identity is included).
    Returns R×4×4 pure rotations, R = nx·ny·nz (27 for the default 3×3×3); index R//2 is the identity.
    """
    angles = candidate_angles(steps_deg, counts, dtype=torch.float64)  # R×3 (rx, ry, rz)
    R = se3.euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2])  # R×3×3
    T = se3.from_rt(R, torch.zeros(len(angles), 3, dtype=torch.float64))  # R×4×4
    return T.to(dtype=dtype, device=device)
