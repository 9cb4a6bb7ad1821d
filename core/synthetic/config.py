"""WorldConfig: every knob of the built-in synthetic world, with defaults per preset.

The world is sampled in the frame `ref0` (the ego's gravity-aligned reference frame at the first step:
X right, Y down, Z forward, the ground plane at y = +preset.ground_y); `world` is `ref0` moved by a
random yaw and horizontal offset, so consumers must use `world_T_ref` rather than assume identity.
Units: metres, radians, seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

from core.presets import Preset


@dataclass(frozen=True)
class WorldConfig:
    """Counts, sizes, speeds, camera rig and textures of the synthetic world (keyword-only)."""

    # --- time
    dt: float = 0.2                                    # seconds between steps
    # --- vehicles (the records' objects)
    max_objects: int = 8                               # K: rows of `boxes` (zero-padded)
    num_vehicles: tuple[int, int] = (3, 8)             # inclusive range, clipped to max_objects
    moving_fraction: float = 0.5                       # chance that each vehicle drives (~3 % of records have none)
    vehicle_length: tuple[float, float] = (3.5, 5.0)   # lx
    vehicle_height: tuple[float, float] = (1.4, 1.9)   # ly
    vehicle_width: tuple[float, float] = (1.6, 2.1)    # lz
    vehicle_speed: tuple[float, float] = (2.0, 8.0)    # m/s along the vehicle's heading (+x of the object)
    vehicle_yaw_rate: float = 0.3                      # |rad/s| bound for moving vehicles
    vehicle_area: float = 12.0                         # vehicles start within ±this (x, z) of ref0, metres
    # --- street layout and static structures (not objects: they are background)
    road_half_width: float = 4.0                       # road along ref0 z, |x| < this
    sidewalk_width: float = 2.5
    num_buildings: tuple[int, int] = (2, 6)
    num_walls: tuple[int, int] = (0, 3)
    num_poles: tuple[int, int] = (2, 6)
    camera_clearance: float = 1.5                      # structures keep this far from every camera
    # --- ego
    ego_speed: tuple[float, float] = (2.0, 6.0)        # m/s when the ego moves
    ego_yaw_rate: float = 0.15                         # |rad/s| bound when the ego moves
    world_offset: float = 50.0                         # |x|, |z| bound of the random ref0 -> world shift
    # --- camera rig (viewpoints on a hemisphere around the ego, anchored to it)
    rig_azimuths: int = 12                             # lattice of rig_azimuths × rig_elevations viewpoints
    rig_elevation_deg: tuple[float, float] = (10.0, 40.0)
    rig_elevations: int = 3
    rig_radius: tuple[float, float] = (12.0, 20.0)
    rig_target_jitter: float = 1.0                     # metres of look-at target noise around the grid centre
    rig_rotation_noise_deg: float = 2.0
    rig_translation_noise: float = 0.3
    # --- rendering and sensor
    max_depth: float = 80.0                            # depth beyond this reads 0 (no return)
    sparse_row_step: int = 4                           # LiDAR-like: keep every n-th image row
    sparse_dropout: float = 0.1                        # ...and drop this fraction of the kept returns
    tile: int = 16                                     # ray-casting tile edge (pixels) for box culling
    # camera photometrics (photometrics.py; 0 = off, the renderer's view-independent colour as is)
    exposure_std: float = 0.0                          # std of each image's log gain (auto-exposure)
    white_balance_std: float = 0.0                     # std of each image's per-channel log gain
    pixel_noise_std: float = 0.0                       # per-pixel Gaussian noise, in [0, 1] colour units
    # --- textures: feature sizes in metres of the checker / stripes / noise patterns on objects
    texture_scale: tuple[float, float] = (0.3, 1.2)
    ground_noise_scale: float = 0.6

    def __post_init__(self) -> None:
        lo, hi = self.num_vehicles
        if not (1 <= lo <= hi):
            raise ValueError(f"num_vehicles must satisfy 1 <= lo <= hi, got {self.num_vehicles}")
        if self.max_objects < 1:
            raise ValueError(f"max_objects must be >= 1, got {self.max_objects}")
        if not (0.0 <= self.moving_fraction <= 1.0):
            raise ValueError(f"moving_fraction must be in [0, 1], got {self.moving_fraction}")
        if self.dt <= 0 or self.max_depth <= 0 or self.tile < 1 or self.sparse_row_step < 1:
            raise ValueError("dt, max_depth, tile and sparse_row_step must be positive")
        for name in ("exposure_std", "white_balance_std", "pixel_noise_std"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not value >= 0:
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        scale = self.texture_scale
        if (not isinstance(scale, tuple) or len(scale) != 2 or not all(isinstance(v, (int, float)) for v in scale)
                or not 0.0 < scale[0] <= scale[1]):
            raise ValueError(f"texture_scale must be (lo, hi) metres with 0 < lo <= hi, got {scale!r}")
        e0, e1 = self.rig_elevation_deg
        if not (0.0 < e0 <= e1 < 90.0):
            raise ValueError(f"rig_elevation_deg must lie in (0, 90), got {self.rig_elevation_deg}")

    @property
    def rig_viewpoints(self) -> int:
        return self.rig_azimuths * self.rig_elevations

    def with_overrides(self, **kwargs) -> "WorldConfig":
        return replace(self, **kwargs)


def world_with(preset: Preset, overrides: dict) -> WorldConfig:
    """The preset's world with `overrides` ({WorldConfig field: value}, lists for tuples as JSON gives them)
    applied; an unknown field or a bad value is a ValueError naming it."""
    known = {f.name for f in fields(WorldConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"unknown WorldConfig field(s) {unknown}; known: {sorted(known)}")
    values = {k: tuple(v) if isinstance(v, list) else v for k, v in overrides.items()}
    return default_world_config(preset).with_overrides(**values)


def default_world_config(preset: Preset) -> WorldConfig:
    """The world used for `preset`: texture feature sizes follow the voxel size so that finer grids
    see finer patterns (at least ~1 voxel per pattern cell)."""
    voxel = preset.grid.voxel_size
    lo = max(0.3, voxel)
    return WorldConfig(texture_scale=(lo, max(lo * 2.5, 1.2)), ground_noise_scale=max(0.5, voxel * 0.75),
                       vehicle_area=min(12.0, 0.75 * min(preset.grid.xmax, -preset.grid.xmin,
                                                         preset.grid.zmax, -preset.grid.zmin)))


DEG = math.pi / 180.0
