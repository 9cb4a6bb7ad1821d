"""generate_record: sample a scene, render every (step, view), assemble a record (docs/data.md#records).

Frames: boxes in `world` (canonical encoding), `world_T_ref[t]` the ego's gravity-aligned frame at step
t (ground at ref y = +preset.ground_y), `world_T_cam[t, v] = world_T_ref[t] @ ref_T_cam[v]` (the rig is
anchored to the ego). `world` differs from `ref` at step 0 by a random yaw and horizontal shift.
"""

from __future__ import annotations

import numpy as np
import torch

from core.geometry import boxes as gboxes
from core.geometry import camera, se3
from core.presets import Preset
from core.synthetic.config import WorldConfig, default_world_config
from core.synthetic.photometrics import apply_photometrics
from core.synthetic.render import render
from core.synthetic.scene import sample_scene
from core.synthetic.sensor import add_depth_noise, sparsify_rows
from core.synthetic.textures import noise_lattice


def generate_record(preset: Preset, *, seed: int, num_views: int | None = None, num_frames: int | None = None,
                    moving_ego: bool = False, sparse_depth: bool = False, noise: float = 0.0,
                    device: str | torch.device = "cpu", world: WorldConfig | None = None) -> dict[str, np.ndarray]:
    """One synthetic RGB-D record (T = num_frames or preset.num_frames steps, V = num_views or
    preset.num_views cameras, H×W from preset.camera, K = world.max_objects box rows).

    Keys (docs/data.md#records): rgb uint8 T×V×H×W×3, depth float32 T×V×H×W (metres along Z, 0 = none),
    pix_T_cam float32 V×4×4, world_T_cam float32 T×V×4×4, world_T_ref float32 T×4×4, boxes float32
    T×K×7 (world), box_valid bool T×K, box_id int32 K (1..n, -1 for padding rows), box_moving bool K.

    Deterministic by `seed` (same seed, same device ⇒ identical arrays). At least one object lies
    entirely inside the preset's grid (in `ref` of that step) at every step. `sparse_depth` keeps
    LiDAR-like rows only; `noise` is the std (metres) of Gaussian depth noise; `device` is where the
    ray casting runs (e.g. "cuda"); `world` overrides the preset's world (camera photometrics, textures, …).
    """
    cfg = world if world is not None else default_world_config(preset)
    T = int(num_frames if num_frames is not None else preset.num_frames)
    V = int(num_views if num_views is not None else preset.num_views)
    if T < 1 or V < 1:
        raise ValueError(f"num_frames and num_views must be >= 1, got T={T}, V={V}")
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if noise < 0:
        raise ValueError(f"noise (depth std, metres) must be >= 0, got {noise}")
    H, W = preset.camera.H, preset.camera.W
    K = cfg.max_objects
    rng = np.random.default_rng(int(seed))
    scene = sample_scene(rng, T=T, V=V, cfg=cfg, grid=preset.grid, ground_y=preset.ground_y, moving_ego=moving_ego)

    # Poses (float64 while composing, then float32: the renderer uses exactly the stored values).
    world_T_ref = scene.world_T_ref0 @ scene.ref0_T_ref  # T×4×4
    world_T_cam = world_T_ref[:, None] @ scene.ref_T_cam[None]  # T×V×4×4
    n = scene.vehicles.shape[1]
    vehicles_world = gboxes.transform_boxes(scene.world_T_ref0.expand(T, 4, 4), scene.vehicles)  # T×n×7
    structures_world = gboxes.transform_boxes(scene.world_T_ref0[None], scene.structures[None])[0]  # m×7
    pix_T_cam = camera.intrinsics_from_fov(H, W, preset.camera.hfov_deg).expand(V, 4, 4)  # V×4×4

    rec_world_T_ref = world_T_ref.float()
    rec_world_T_cam = world_T_cam.float()
    rec_vehicles = vehicles_world.float()

    # Render all T·V cameras at once; camera c = t·V + v sees the boxes of step t.
    dev = torch.device(device)
    gen = torch.Generator().manual_seed(int(rng.integers(2**62)))  # CPU draws: same on every device
    lattice = noise_lattice(gen, dev)
    everything = torch.cat([rec_vehicles, structures_world.float().expand(T, -1, 7)], dim=1)  # T×B×7
    B = everything.shape[1]
    rgb, depth = render(
        pix_T_cam=pix_T_cam.repeat(T, 1, 1).to(dev),  # T·V×4×4
        world_T_cam=rec_world_T_cam.reshape(T * V, 4, 4).to(dev),  # T·V×4×4
        H=H, W=W,
        boxes_world=everything.repeat_interleave(V, dim=0).to(dev),  # T·V×B×7
        box_valid=torch.ones(T * V, B, dtype=torch.bool, device=dev),
        box_textures=scene.textures.float().to(dev),
        ref0_T_world=se3.invert(scene.world_T_ref0).float().to(dev),
        ground_y=float(preset.ground_y), lattice=lattice, cfg=cfg,
    )

    if sparse_depth:
        depth = sparsify_rows(depth, row_step=cfg.sparse_row_step, dropout=cfg.sparse_dropout, generator=gen)
    depth = add_depth_noise(depth, std=float(noise), generator=gen)
    # After every other draw of `gen`, and none when off: records without photometrics stay as they were.
    rgb = apply_photometrics(rgb, exposure_std=cfg.exposure_std, white_balance_std=cfg.white_balance_std,
                             pixel_noise_std=cfg.pixel_noise_std, generator=gen)

    boxes = np.zeros((T, K, 7), np.float32)
    boxes[:, :n] = rec_vehicles.numpy()
    box_valid = np.zeros((T, K), np.bool_)
    box_valid[:, :n] = True
    box_id = np.full((K,), -1, np.int32)
    box_id[:n] = np.arange(1, n + 1, dtype=np.int32)
    box_moving = np.zeros((K,), np.bool_)
    box_moving[:n] = scene.vehicle_moving
    return {
        "rgb": (rgb * 255.0).round().to(torch.uint8).reshape(T, V, H, W, 3).cpu().numpy(),
        "depth": depth.float().reshape(T, V, H, W).cpu().numpy(),
        "pix_T_cam": pix_T_cam.float().contiguous().numpy(),
        "world_T_cam": rec_world_T_cam.numpy(),
        "world_T_ref": rec_world_T_ref.numpy(),
        "boxes": boxes,
        "box_valid": box_valid,
        "box_id": box_id,
        "box_moving": box_moving,
    }
