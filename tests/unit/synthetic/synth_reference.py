"""Slow, obvious references shared by the synthetic-world tests: one ray at a time, plain Python floats."""

from __future__ import annotations

import math

import numpy as np


def yaw_matrix(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def pixel_ray(pix_T_cam: np.ndarray, world_T_cam: np.ndarray, u: float, v: float) -> tuple[np.ndarray, np.ndarray]:
    """World origin and direction (cam-Z component 1) of the ray through pixel centre (u, v)."""
    fx, fy, cx, cy = pix_T_cam[0, 0], pix_T_cam[1, 1], pix_T_cam[0, 2], pix_T_cam[1, 2]
    d_cam = np.array([(u - cx) / fx, (v - cy) / fy, 1.0])
    return world_T_cam[:3, 3].astype(np.float64), world_T_cam[:3, :3].astype(np.float64) @ d_cam


def ray_box(origin: np.ndarray, d: np.ndarray, box: np.ndarray, near: float = 1e-3) -> float:
    """Entry parameter of the ray o + t·d into the oriented box (x, y, z, lx, ly, lz, yaw); inf on a miss."""
    R = yaw_matrix(float(box[6]))
    o_l = R.T @ (origin - box[:3])
    d_l = R.T @ d
    t_enter, t_exit = -math.inf, math.inf
    for k in range(3):
        h = 0.5 * float(box[3 + k])
        if abs(d_l[k]) < 1e-15:
            if abs(o_l[k]) > h:
                return math.inf
            continue
        a, b = (-h - o_l[k]) / d_l[k], (h - o_l[k]) / d_l[k]
        t_enter, t_exit = max(t_enter, min(a, b)), min(t_exit, max(a, b))
    return t_enter if (t_exit >= t_enter and t_enter > near) else math.inf


def ray_ground(origin: np.ndarray, d: np.ndarray, ground_y: float, near: float = 1e-3) -> float:
    if d[1] <= 0:
        return math.inf
    t = (ground_y - origin[1]) / d[1]
    return t if t > near else math.inf


def nearest_hit(origin, d, boxes, ground_y) -> tuple[float, int]:
    """(t, index of the nearest box or -1 for the ground / nothing)."""
    best, which = ray_ground(origin, d, ground_y), -1
    for k, box in enumerate(boxes):
        t = ray_box(origin, d, box)
        if t < best:
            best, which = t, k
    return best, which
