"""The camera rig: V viewpoints on a hemisphere around the ego, anchored to it (as the paper's CARLA
data: a lattice of viewpoints on a sphere around the ego car, V of them sampled per episode, each
perturbed a little).

Frames (docs/conventions.md#frames): `ref` is the ego's gravity-aligned frame (X right, Y down, Z forward), `cam`
is OpenCV (X right, Y down, Z forward). "Up" is -Y. Poses are `a_T_b` with p_a = a_T_b @ p_b.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from core.geometry import se3
from core.synthetic.config import DEG, WorldConfig


def look_at(eye: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Camera poses that sit at `eye` and look at `target` with no roll (image rows stay level).

    eye, target: V×3 in `ref` (Y down) -> ref_T_cam: V×4×4 (cam Z towards the target, cam Y down-ish).
    The view direction must not be vertical.
    """
    forward = target - eye
    forward = forward / forward.norm(dim=-1, keepdim=True)  # V×3
    down = torch.zeros_like(forward)
    down[:, 1] = 1.0
    right = torch.linalg.cross(down, forward)  # X = down × Z for a level OpenCV camera
    right = right / right.norm(dim=-1, keepdim=True)
    cam_down = torch.linalg.cross(forward, right)  # Y = Z × X
    R = torch.stack([right, cam_down, forward], dim=-1)  # V×3×3, columns are the cam axes in ref
    return se3.from_rt(R, eye)


def sample_rig(rng: np.random.Generator, num_views: int, cfg: WorldConfig,
               target: tuple[float, float, float]) -> torch.Tensor:
    """Sample V viewpoints from the cfg's azimuth × elevation lattice (without replacement while the
    lattice has enough), each at its own radius, looking at `target` (ref metres) plus jitter, then
    perturbed by a small random rotation and translation.

    Returns ref_T_cam: V×4×4 float64 (CPU).
    """
    n_lattice = cfg.rig_viewpoints
    picks = rng.choice(n_lattice, size=num_views, replace=num_views > n_lattice)
    az_index, el_index = picks % cfg.rig_azimuths, picks // cfg.rig_azimuths
    e0, e1 = cfg.rig_elevation_deg
    el_levels = np.linspace(e0, e1, cfg.rig_elevations) if cfg.rig_elevations > 1 else np.array([0.5 * (e0 + e1)])
    az = 2.0 * math.pi * az_index / cfg.rig_azimuths
    el = el_levels[el_index] * DEG
    radius = rng.uniform(*cfg.rig_radius, size=num_views)
    centre = np.asarray(target, np.float64)
    aim = centre + rng.uniform(-cfg.rig_target_jitter, cfg.rig_target_jitter, size=(num_views, 3))
    eye = centre + radius[:, None] * np.stack([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)], -1)
    ref_T_cam = look_at(torch.from_numpy(eye), torch.from_numpy(aim))  # V×4×4
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))
    noise = se3.random_rigid(num_views, cfg.rig_rotation_noise_deg * DEG, cfg.rig_translation_noise,
                             gen, dtype=torch.float64)
    # Perturb in the camera's own frame: the view wobbles about its centre and shifts a little.
    return ref_T_cam @ noise
