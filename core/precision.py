"""Geometry in float32 under mixed precision: `full_precision` runs a function outside torch.autocast.

Why: `n3dmap train --precision bf16` runs a task's forward under torch.autocast(bfloat16), and autocast
casts every matmul (`@`, bmm, einsum) to bf16, the ones in core.geometry included: poses, point clouds
and sampling coordinates then carry 8 significant bits. A coordinate of 20 m is off by up to 6 cm, a
pixel coordinate of 300 by 1 px, and `sample_volume_at` / `sample_image` cast their coordinates to the
dtype of the (bf16) volume they sample. Measured on tiny (untrained weights, one batch of 2, the same
random draws, 1 thread): with the geometry under autocast, the 3D encoder's input volume (built from
depth, poses and image samples) differed from fp32's by 53-67 % (occupancy channel) and 9-20 % (RGB
channels, relative L2), its first conv's output by 33-44 %, and the task losses by up to 9 % (egomotion
8.9 %, detector 8.6 %, flow 3.9 %, pretrain 2.4-3.0 %; occupancy 0.0 %). With the geometry in float32
the input volume is identical, the first conv differs by 0.2 % (bf16 rounding of the conv alone) and
every loss by at most 0.3 %. The learned networks are where bf16 pays; the geometry costs little, so it
stays float32: decorated functions see float32 inputs (bf16/fp16 tensors upcast; float64 kept) and run
with autocast off, so their outputs are float32. Outside autocast the decorator only checks whether
autocast is on and calls the function unchanged.
"""

from __future__ import annotations

import functools
from typing import Callable, TypeVar

import torch

F = TypeVar("F", bound=Callable)
_LOW = (torch.bfloat16, torch.float16)


def _up(value):
    if isinstance(value, torch.Tensor) and value.dtype in _LOW:
        return value.float()
    if isinstance(value, (list, tuple)) and any(isinstance(v, torch.Tensor) and v.dtype in _LOW for v in value):
        return type(value)(_up(v) for v in value)
    return value


def _device_type(args, kwargs) -> str | None:
    for value in (*args, *kwargs.values()):
        if isinstance(value, torch.Tensor):
            return value.device.type
    return None


def full_precision(fn: F) -> F:
    """Decorator: under autocast (of the first tensor argument's device type), call `fn` with autocast
    off and its bf16/fp16 tensor arguments (also inside lists/tuples) upcast to float32."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        device_type = _device_type(args, kwargs)
        if device_type is None or not torch.is_autocast_enabled(device_type):
            return fn(*args, **kwargs)
        with torch.autocast(device_type, enabled=False):
            return fn(*(_up(a) for a in args), **{k: _up(v) for k, v in kwargs.items()})

    return wrapper  # type: ignore[return-value]


def geometry_dtype(dtype: torch.dtype) -> torch.dtype:
    """The dtype geometry derived from a tensor of `dtype` should use: float32 for bf16/fp16 (network
    outputs under autocast), else `dtype` (float64 stays float64)."""
    return torch.float32 if dtype in _LOW else dtype
