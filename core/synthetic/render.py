"""Render RGB + depth of the synthetic world for a batch of cameras (ray casting + Lambertian shading).

Frames (docs/conventions.md#frames): `world` gravity-aligned with Y down; `ref0` (the ego frame of step 0) differs
from it by a yaw and a horizontal shift only, so the ground is the plane y = ground_y in both; `cam`
is OpenCV. Depth is metres along camera Z, 0 = no return (nothing hit, or beyond `max_depth`).
Colour = albedo (textures.py) × (ambient + a sun + a fill light), so the faces of a box differ.
"""

from __future__ import annotations

import torch

from core.geometry import boxes as gboxes
from core.geometry import se3
from core.synthetic import textures as tex
from core.synthetic.config import WorldConfig
from core.synthetic.raycast import cast_boxes, cast_ground, ray_affine, tile_pixels, tiles_to_image

# Directions towards the lights (up is -Y): a sun and a weaker fill from the other side.
_SUN = (0.35, -1.0, 0.55)
_FILL = (-0.6, -0.3, -0.4)
_AMBIENT, _SUN_GAIN, _FILL_GAIN = 0.35, 0.5, 0.2


def _lambert(normals: torch.Tensor) -> torch.Tensor:
    """N×3 unit normals -> N×1 light factor (lights given in the normals' frame, yaw-invariant enough)."""
    sun = torch.tensor(_SUN, dtype=normals.dtype, device=normals.device)
    fill = torch.tensor(_FILL, dtype=normals.dtype, device=normals.device)
    sun, fill = sun / sun.norm(), fill / fill.norm()
    return (_AMBIENT + _SUN_GAIN * (normals @ sun).clamp_min(0) + _FILL_GAIN * (normals @ fill).clamp_min(0)).unsqueeze(-1)


def render(*, pix_T_cam: torch.Tensor, world_T_cam: torch.Tensor, H: int, W: int, boxes_world: torch.Tensor,
           box_valid: torch.Tensor, box_textures: torch.Tensor, ref0_T_world: torch.Tensor, ground_y: float,
           lattice: torch.Tensor, cfg: WorldConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Ray-cast C cameras.

    pix_T_cam, world_T_cam: C×4×4; boxes_world: C×B×7 (what camera c sees); box_valid: C×B;
    box_textures: B×N_TEX (one row per box column); ref0_T_world: 4×4 (a yaw + horizontal shift; ground
    texture coordinates); lattice: `textures.noise_lattice`
    -> (rgb: C×H×W×3 float in [0, 1], depth: C×H×W float, 0 = no return). Device/dtype follow pix_T_cam.
    """
    C = pix_T_cam.shape[0]
    dtype, device = pix_T_cam.dtype, pix_T_cam.device
    tile = cfg.tile
    u, v = tile_pixels(H, W, tile, dtype=dtype, device=device)  # N each, tile-major
    t_box, box_index = cast_boxes(pix_T_cam, world_T_cam, boxes_world, box_valid, H, W, tile=tile)  # C×N

    # Ground and sky in ref0 (ground at y = ground_y, road along ref0 z); textures only where seen.
    origin, A = ray_affine(pix_T_cam, ref0_T_world @ world_T_cam)  # C×3, C×3×3
    t_ground, d_y = cast_ground(origin, A, u, v, ground_y)  # C×N
    d_x = A[:, 0, 0:1] * u + A[:, 0, 1:2] * v + A[:, 0, 2:3]  # C×N
    d_z = A[:, 2, 0:1] * u + A[:, 2, 1:2] * v + A[:, 2, 2:3]
    hit_box = t_box < t_ground  # C×N (inf < inf is False)
    t = torch.minimum(t_box, t_ground)
    N = u.shape[0]
    rgb = torch.empty(C * N, 3, dtype=dtype, device=device)
    on_ground = (torch.isfinite(t_ground) & ~hit_box).reshape(-1).nonzero(as_tuple=True)[0]  # Ng flat indices
    if on_ground.numel() > 0:
        cam = on_ground // N
        tg = t_ground.reshape(-1).index_select(0, on_ground)
        gx = origin[:, 0].index_select(0, cam) + tg * d_x.reshape(-1).index_select(0, on_ground)  # Ng
        gz = origin[:, 2].index_select(0, cam) + tg * d_z.reshape(-1).index_select(0, on_ground)
        albedo = tex.ground_albedo(gx, gz, lattice, road_half_width=cfg.road_half_width,
                                   sidewalk_width=cfg.sidewalk_width, noise_scale=cfg.ground_noise_scale)  # Ng×3
        up = torch.tensor([[0.0, -1.0, 0.0]], dtype=dtype, device=device)
        rgb.index_copy_(0, on_ground, albedo * _lambert(up))
    in_sky = (~torch.isfinite(t)).reshape(-1).nonzero(as_tuple=True)[0]  # Ns
    if in_sky.numel() > 0:
        sx, sy, sz = (d.reshape(-1).index_select(0, in_sky) for d in (d_x, d_y, d_z))
        rgb.index_copy_(0, in_sky, tex.sky_colour(-sy / torch.sqrt(sx * sx + sy * sy + sz * sz)))

    # Boxes: texture in the object frame, normal of the face that was hit.
    hits = hit_box.reshape(-1).nonzero(as_tuple=True)[0]  # Nb flat indices into C·N
    if hits.numel() > 0:
        B = boxes_world.shape[1]
        cam, pix = hits // N, hits % N
        b = box_index.reshape(-1).index_select(0, hits)  # Nb
        # Per (camera, box) pair: ray origin and ray map in the object frame, rotation obj -> ref0.
        o_w, A_w = ray_affine(pix_T_cam, world_T_cam)  # C×3, C×3×3
        obj_T_world = se3.invert(gboxes.box_T_obj(boxes_world))  # C×B×4×4
        R_ow = obj_T_world[..., :3, :3]  # C×B×3×3
        o_loc = (R_ow @ o_w[:, None, :, None]).squeeze(-1) + obj_T_world[..., :3, 3]  # C×B×3
        A_loc = R_ow @ A_w[:, None]  # C×B×3×3
        R_ref0_obj = ref0_T_world[:3, :3] @ R_ow.transpose(-1, -2)  # C×B×3×3 (lights are fixed in ref0)
        table = torch.cat([o_loc, A_loc.flatten(-2), R_ref0_obj.flatten(-2), 0.5 * boxes_world[..., 3:6]],
                          dim=-1).reshape(C * B, 24)  # C·B×24
        rows = table.index_select(0, cam * B + b)  # Nb×24
        pu, pv = u.index_select(0, pix).unsqueeze(-1), v.index_select(0, pix).unsqueeze(-1)  # Nb×1
        d_loc = rows[:, 3:12:3] * pu + rows[:, 4:12:3] * pv + rows[:, 5:12:3]  # Nb×3, A_loc @ (u, v, 1)
        p_local = rows[:, 0:3] + t_box.reshape(-1).index_select(0, hits).unsqueeze(-1) * d_loc  # Nb×3
        half = rows[:, 21:24]  # Nb×3
        face_axis = (p_local.abs() / half).argmax(-1)  # Nb: the face the point lies on
        sign = torch.gather(p_local, 1, face_axis.unsqueeze(-1)).sign()  # Nb×1
        R = rows[:, 12:21].reshape(-1, 3, 3)  # Nb×3×3
        normal = torch.gather(R, 2, face_axis.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1) * sign  # Nb×3, ref0
        albedo = tex.object_albedo(p_local, face_axis, half, box_textures.index_select(0, b), lattice)
        rgb.index_copy_(0, hits, albedo * _lambert(normal))

    depth = torch.where(t <= cfg.max_depth, t, 0.0)  # C×N (inf: no hit)
    rgb = tiles_to_image(rgb.reshape(C, -1, 3).clamp(0.0, 1.0), H, W, tile)  # C×H×W×3
    return rgb, tiles_to_image(depth, H, W, tile)
